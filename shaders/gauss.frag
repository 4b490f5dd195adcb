// splatdeform: a Gaussian's footprint, premultiplied (blend ONE, ONE_MINUS_SRC_ALPHA).
//   alpha = min(0.99, opacity * exp(-0.5 d^T conic d)); fragments below 1/255 are dropped.
// The host prepends "#version 330 core".

flat in vec4 g_color;
flat in vec3 g_conic;
flat in vec2 g_center;

out vec4 f_color;

void main() {
    vec2 d = gl_FragCoord.xy - g_center;
    float power = -0.5 * (g_conic.x * d.x * d.x + g_conic.z * d.y * d.y) - g_conic.y * d.x * d.y;
    if (power > 0.0) {
        discard;
    }
    float alpha = min(0.99, g_color.a * exp(power));
    if (alpha < 1.0 / 255.0) {
        discard;
    }
    f_color = vec4(g_color.rgb * alpha, alpha);
}
