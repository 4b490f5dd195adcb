// splatdeform: eye-dome lighting (Boucheny 2009), the depth cue of LiDAR viewers for points
// without normals: a pixel darkens by how much its neighbours two pixels away lie in front of
// it (log view depth), so silhouettes and steps in depth get dark outlines and a flat-shaded
// cloud reads as a surface. Appended after surfel_resolve.frag (uses its view_depth and
// uniforms; that file declares eye_dome). Background neighbours count as far away.

const float EDL_STRENGTH = 60.0;
const float EDL_RADIUS = 2.0;

float eye_dome(ivec2 pixel, float depth) {
    if (depth >= 1e29) {
        return 1.0;
    }
    ivec2 last = ivec2(u_viewport) - 1;
    float mine = log(depth);
    float response = 0.0;
    const vec2 dirs[8] = vec2[8](vec2(1.0, 0.0), vec2(0.7071, 0.7071), vec2(0.0, 1.0),
                                 vec2(-0.7071, 0.7071), vec2(-1.0, 0.0), vec2(-0.7071, -0.7071),
                                 vec2(0.0, -1.0), vec2(0.7071, -0.7071));
    for (int i = 0; i < 8; ++i) {
        ivec2 q = clamp(pixel + ivec2(round(dirs[i] * EDL_RADIUS)), ivec2(0), last);
        float nb = texelFetch(u_color, q, 0).a > 0.0 ? view_depth(q) : 1e30;
        response += max(0.0, mine - log(nb));
    }
    return exp(-EDL_STRENGTH * response / 8.0);
}
