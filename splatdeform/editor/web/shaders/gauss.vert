// splatdeform editor page: 3D Gaussian splats deformed in the vertex stage, the WebGL2 twin of
// shaders/gauss.vert (no geometry shader: one point sprite per splat, square, covering 3 sigma,
// in depth order). Vertex s draws splat u_order[s] (the page sorts the slots back to front). Per splat 4 texels of u_splat:
// [x y z opacity] [xx xy xz yy] [yz zz label spread] [r g b mean]; SH_TEXELS texels of u_sh
// (f_rest, channel-major). spread, mean: of the splat's float64 log-scales (covariance.glsl's
// ``shape``). The host prepends "#define K", "#define SH_DEGREE", "#define SH_REST",
// "#define SH_TEXELS", "#define COVARIANCE m" (the edit's gaussians.covariance), deform.glsl,
// shaders/covariance.glsl, covariance_page.glsl and shading.glsl.
uniform highp sampler2D u_order;
uniform int u_order_width;
uniform highp sampler2D u_splat;
uniform int u_splat_width;
#if SH_DEGREE > 0
uniform highp sampler2D u_sh;
uniform int u_sh_width;
#endif
uniform mat4 viewMatrix;
uniform mat4 projectionMatrix;
uniform vec3 cameraPosition;
uniform vec2 u_viewport;
out vec4 v_color;
out vec3 v_conic;
out vec2 v_center;

const float LOW_PASS = 0.3;
const float SH_C1 = 0.4886025119029199;

vec4 splat_texel(int i, int j) {
    int t = 4 * i + j;
    return texelFetch(u_splat, ivec2(t % u_splat_width, t / u_splat_width), 0);
}

#if SH_DEGREE > 0
float sh_at(int i, int f) {
    int t = i * SH_TEXELS + f / 4;
    return texelFetch(u_sh, ivec2(t % u_sh_width, t / u_sh_width), 0)[f % 4];
}
vec3 sh_coeff(int i, int j) {  // j = 1 .. SH_REST
    return vec3(sh_at(i, j - 1), sh_at(i, SH_REST + j - 1), sh_at(i, 2 * SH_REST + j - 1));
}
vec3 sh_view(int i, vec3 d) {
    float x = d.x, y = d.y, z = d.z;
    vec3 c = -SH_C1 * y * sh_coeff(i, 1) + SH_C1 * z * sh_coeff(i, 2) - SH_C1 * x * sh_coeff(i, 3);
#if SH_DEGREE > 1
    float xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
    c += 1.0925484305920792 * xy * sh_coeff(i, 4) - 1.0925484305920792 * yz * sh_coeff(i, 5)
       + 0.31539156525252005 * (2.0 * zz - xx - yy) * sh_coeff(i, 6)
       - 1.0925484305920792 * xz * sh_coeff(i, 7) + 0.5462742152960396 * (xx - yy) * sh_coeff(i, 8);
#if SH_DEGREE > 2
    c += -0.5900435899266435 * y * (3.0 * xx - yy) * sh_coeff(i, 9)
       + 2.890611442640554 * xy * z * sh_coeff(i, 10)
       - 0.4570457994644658 * y * (4.0 * zz - xx - yy) * sh_coeff(i, 11)
       + 0.3731763325901154 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh_coeff(i, 12)
       - 0.4570457994644658 * x * (4.0 * zz - xx - yy) * sh_coeff(i, 13)
       + 1.445305721320277 * z * (xx - yy) * sh_coeff(i, 14)
       - 0.5900435899266435 * x * (xx - 3.0 * yy) * sh_coeff(i, 15);
#endif
#endif
    return c;
}
#endif

void main() {
    int slot = gl_VertexID;
    int ot = slot / 4;
    int i = int(texelFetch(u_order, ivec2(ot % u_order_width, ot / u_order_width), 0)[slot % 4] + 0.5);
    vec4 t0 = splat_texel(i, 0), t1 = splat_texel(i, 1), t2 = splat_texel(i, 2),
         t3 = splat_texel(i, 3);
    vec3 p = t0.xyz;
    mat3 sigma = mat3(t1.x, t1.y, t1.z, t1.y, t1.w, t2.x, t1.z, t2.x, t2.y);
    mat3 J = deform_point(i, p);
    bool moved = J != mat3(1.0);  // fixed splats (and no fit): Sigma as it is
    if (moved) sigma = page_covariance(J, sigma, vec2(t2.w, t3.w));
    gl_Position = vec4(0.0, 0.0, 2.0, 1.0);  // culled unless set below
    v_color = vec4(0.0);
    vec3 t = (viewMatrix * vec4(p, 1.0)).xyz;
    float z = -t.z;
    if (z <= 1e-4) return;
    float fx = 0.5 * u_viewport.x * projectionMatrix[0][0];
    float fy = 0.5 * u_viewport.y * projectionMatrix[1][1];
    float limx = 1.3 / projectionMatrix[0][0];
    float limy = 1.3 / projectionMatrix[1][1];
    float tx = clamp(t.x / z, -limx, limx) * z;
    float ty = clamp(t.y / z, -limy, limy) * z;
    mat3 Jp = mat3(fx / z, 0.0, 0.0, 0.0, fy / z, 0.0, fx * tx / (z * z), fy * ty / (z * z), 0.0);
    mat3 T = Jp * mat3(viewMatrix);
    mat3 cov = T * sigma * transpose(T);
    float a = cov[0][0] + LOW_PASS, b = cov[0][1], c = cov[1][1] + LOW_PASS;
    float det = a * c - b * b;
    if (!(det > 0.0)) return;
    v_conic = vec3(c, -b, a) / det;
    v_center = vec2(fx * t.x / z + 0.5 * u_viewport.x, fy * t.y / z + 0.5 * u_viewport.y);
    gl_Position = projectionMatrix * vec4(t, 1.0);
    float lmax = 0.5 * (a + c) + sqrt(0.25 * (a - c) * (a - c) + b * b);  // 2D eigenvalue
    gl_PointSize = min(6.0 * sqrt(lmax), 1024.0);  // 3 sigma each side
    vec3 rgb = t3.rgb;
#if SH_DEGREE > 0
    vec3 d = normalize(p - cameraPosition);
    if (moved) d = transpose(polar_rotation(J)) * d;  // SH turn with R in every mode
    rgb += sh_view(i, d);
#endif
    v_color = vec4(region_tint(max(rgb, 0.0), t2.z), t0.w);
}
