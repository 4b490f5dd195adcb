precision highp float;
in vec4 v_color;
in vec3 v_conic;
in vec2 v_center;
out vec4 frag;
void main() {
    vec2 d = gl_FragCoord.xy - v_center;
    float power = -0.5 * (v_conic.x * d.x * d.x + v_conic.z * d.y * d.y) - v_conic.y * d.x * d.y;
    if (power > 0.0) discard;
    float alpha = min(0.99, v_color.a * exp(power));
    if (alpha < 1.0 / 255.0) discard;
    frag = vec4(v_color.rgb * alpha, alpha);  // premultiplied, back to front
}
