// splatdeform editor page: meshes lit by their deformed face normals (from the view-space
// position's screen derivatives, so files without normals are shaded too).
precision highp float;
in vec3 v_color;
in vec3 v_view_pos;
out vec4 frag;
void main() {
    vec3 n = normalize(cross(dFdx(v_view_pos), dFdy(v_view_pos)));
    frag = vec4(lit(v_color, n), 1.0);
}
