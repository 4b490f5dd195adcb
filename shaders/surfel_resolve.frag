// splatdeform: surface splatting pass 3: normalise the accumulated colour and normal, shade.
// Screen-space hole filling (as in point rendering): a pixel that no splat reached, or whose
// surface lies clearly behind (> HOLE_DEPTH relative) at least 6 of its 8 neighbours -- a
// one-pixel hole in the front surface, seen through -- takes the mean of those neighbours.
// Pixels left empty keep the background and alpha 0. Pixels of splats without normals (large
// clouds drawn as flat discs) get eye-dome lighting (edl.glsl, appended by the host).
// The host prepends "#version 330 core" and shading.glsl.

uniform sampler2D u_color;    // (sum w colour, sum w)
uniform sampler2D u_normal;   // (sum w normal, sum w)
uniform sampler2D u_depth;    // depth pre-pass (window depth in [0, 1])
uniform vec2 u_viewport;
uniform vec2 u_proj_scale;    // projection[0][0], projection[1][1]
uniform vec2 u_near_far;
uniform vec3 u_background;

out vec4 f_color;

const float HOLE_DEPTH = 0.02;

float eye_dome(ivec2 pixel, float depth);   // edl.glsl

float view_depth(ivec2 p) {
    float d = texelFetch(u_depth, p, 0).r;
    if (d >= 1.0) {
        return 1e30;
    }
    float n = u_near_far.x, f = u_near_far.y;
    return 2.0 * n * f / (f + n - (2.0 * d - 1.0) * (f - n));
}

void main() {
    ivec2 pixel = ivec2(gl_FragCoord.xy);
    ivec2 last = ivec2(u_viewport) - 1;
    vec4 acc = texelFetch(u_color, pixel, 0);
    vec3 normal = texelFetch(u_normal, pixel, 0).xyz;
    float mine = acc.a > 0.0 ? view_depth(pixel) : 1e30;
    vec3 color_sum = vec3(0.0);
    vec3 normal_sum = vec3(0.0);
    int in_front = 0;
    for (int dy = -1; dy <= 1; ++dy) {
        for (int dx = -1; dx <= 1; ++dx) {
            if (dx == 0 && dy == 0) {
                continue;
            }
            ivec2 q = clamp(pixel + ivec2(dx, dy), ivec2(0), last);
            vec4 nb = texelFetch(u_color, q, 0);
            if (nb.a <= 0.0) {
                continue;
            }
            float depth = view_depth(q);
            if (depth < mine - HOLE_DEPTH * depth) {
                in_front += 1;
                color_sum += nb.rgb / nb.a;
                normal_sum += normalize(texelFetch(u_normal, q, 0).xyz + 1e-30);
            }
        }
    }
    vec3 color;
    if (in_front >= 6) {
        color = color_sum / float(in_front);
        normal = normal_sum;
    } else if (acc.a > 0.0) {
        color = acc.rgb / acc.a;
    } else {
        f_color = vec4(u_background, 0.0);
        return;
    }
    vec2 ndc = gl_FragCoord.xy / u_viewport * 2.0 - 1.0;
    vec3 ray = vec3(ndc / u_proj_scale, -1.0);   // view-space direction through this pixel
    float edl = (dot(normal, normal) == 0.0 && acc.a > 0.0) ? eye_dome(pixel, mine) : 1.0;
    f_color = vec4(headlight(color, normal, ray) * edl, 1.0);
}
