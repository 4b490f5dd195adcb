precision highp float;
in vec3 v_color;
in vec3 v_view_pos;
out vec4 frag;
void main() {
    vec2 q = 2.0 * gl_PointCoord - 1.0;
    if (dot(q, q) > 1.0) discard;
    frag = vec4(v_color, 1.0);
}
