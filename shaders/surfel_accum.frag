// splatdeform: surface splatting pass 2: Gaussian-weighted accumulation (additive blending into
// float targets, depth test against the offset pre-pass, no depth writes).
//   w = exp(-2 r^2) on the unit disc (sigma = half the splat radius), 0 outside
//   target 0: (w * colour, w)      target 1: (w * normal facing the viewer, w)
// The host prepends "#version 330 core".

in vec2 g_local;
in vec3 g_normal;      // view space
in vec3 g_view_pos;
in vec3 g_color;

layout(location = 0) out vec4 f_color;
layout(location = 1) out vec4 f_normal;

void main() {
    float r2 = dot(g_local, g_local);
    if (r2 > 1.0) {
        discard;
    }
    float w = exp(-2.0 * r2);
    vec3 n = g_normal;
    if (dot(n, g_view_pos) > 0.0) {
        n = -n;
    }
    f_color = vec4(g_color * w, w);
    f_normal = vec4(n * w, w);
}
