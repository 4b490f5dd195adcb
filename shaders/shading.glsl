// splatdeform: shared headlight shading (Lambert, two-sided, plus ambient).
// Included by the fragment stages (the host pastes it in). A zero normal shades flat.

const float AMBIENT = 0.3;

vec3 headlight(vec3 color, vec3 normal_view, vec3 view_pos) {
    float len = length(normal_view);
    if (len == 0.0) {
        return color;
    }
    vec3 to_eye = normalize(-view_pos);
    float diffuse = abs(dot(normal_view / len, to_eye));
    return color * (AMBIENT + (1.0 - AMBIENT) * diffuse);
}
