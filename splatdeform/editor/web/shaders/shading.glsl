// splatdeform editor page: colour by region and two-sided Lambert shading in view space.
const vec3 FIXED_RGB = vec3(50.0, 110.0, 255.0) / 255.0;
const vec3 HANDLE_RGB = vec3(255.0, 120.0, 30.0) / 255.0;
const float TINT = 0.55;
uniform float u_show_regions;

vec3 region_tint(vec3 c, float label) {
    if (u_show_regions < 0.5 || label < 0.5) return c;
    return mix(c, label < 1.5 ? FIXED_RGB : HANDLE_RGB, TINT);
}

vec3 lit(vec3 c, vec3 n_view) {
    vec3 key = normalize(vec3(0.35, 0.6, 0.72));
    vec3 fill = normalize(vec3(-0.6, -0.2, 0.5));
    float d = 0.62 * abs(dot(n_view, key)) + 0.18 * abs(dot(n_view, fill));
    return c * (0.22 + d);
}
