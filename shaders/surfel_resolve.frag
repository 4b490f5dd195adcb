// splatdeform: surface splatting pass 3: normalise the accumulated colour and normal, shade.
// Pixels no splat reached keep the background and alpha 0.
// The host prepends "#version 330 core" and shading.glsl.

uniform sampler2D u_color;    // (sum w colour, sum w)
uniform sampler2D u_normal;   // (sum w normal, sum w)
uniform vec2 u_viewport;
uniform vec2 u_proj_scale;    // projection[0][0], projection[1][1]
uniform vec3 u_background;

out vec4 f_color;

void main() {
    ivec2 pixel = ivec2(gl_FragCoord.xy);
    vec4 acc = texelFetch(u_color, pixel, 0);
    if (acc.a <= 0.0) {
        f_color = vec4(u_background, 0.0);
        return;
    }
    vec3 normal = texelFetch(u_normal, pixel, 0).xyz;
    vec2 ndc = gl_FragCoord.xy / u_viewport * 2.0 - 1.0;
    vec3 ray = vec3(ndc / u_proj_scale, -1.0);   // view-space direction through this pixel
    f_color = vec4(headlight(acc.rgb / acc.a, normal, ray), 1.0);
}
