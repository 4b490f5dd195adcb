// splatdeform editor page: the deformation of the vertex stage, the WebGL2 twin of
// shaders/deform.glsl (WebGL2 has no storage buffers: the basis is an RGBA32F texture).
//
// The host prepends "#define K k" (k control DOFs; 0 = no fit yet). Per point the basis holds
// K values then 3K gradient components (4K floats = K texels, point i at texels i*K ..), the
// storage layout of shaders/deform.glsl. delta C is uniform vec3 u_delta[K].
//
//   p' = p + sum_k b_k delta_k          J = I + sum_k outer(delta_k, grad b_k)
//   n' = normalize(cof(J) n)
// Gaussians then take Sigma' and the polar rotation R of J (SH at R^T d) from
// shaders/covariance.glsl itself (the ``gaussians.covariance`` modes; served as
// /web/shared/covariance.glsl), pasted after this file.

#if K > 0
uniform highp sampler2D u_basis;
uniform int u_basis_width;
uniform vec3 u_delta[K];

#if K == 4
// one handle: 4 texels, read as vectors (software WebGL runs this faster than the array form)
vec4 basis_texel(int t) {
    return texelFetch(u_basis, ivec2(t % u_basis_width, t / u_basis_width), 0);
}
mat3 deform_point(int i, inout vec3 p) {
    vec4 v = basis_texel(4 * i), g0 = basis_texel(4 * i + 1), g1 = basis_texel(4 * i + 2),
         g2 = basis_texel(4 * i + 3);
    p += v.x * u_delta[0] + v.y * u_delta[1] + v.z * u_delta[2] + v.w * u_delta[3];
    return mat3(1.0) + outerProduct(u_delta[0], g0.xyz)
         + outerProduct(u_delta[1], vec3(g0.w, g1.xy))
         + outerProduct(u_delta[2], vec3(g1.zw, g2.x))
         + outerProduct(u_delta[3], g2.yzw);
}
#else
mat3 deform_point(int i, inout vec3 p) {
    float b[4 * K];
    for (int j = 0; j < K; ++j) {
        int t = i * K + j;
        vec4 v = texelFetch(u_basis, ivec2(t % u_basis_width, t / u_basis_width), 0);
        b[4 * j] = v.x;
        b[4 * j + 1] = v.y;
        b[4 * j + 2] = v.z;
        b[4 * j + 3] = v.w;
    }
    mat3 J = mat3(1.0);
    for (int k = 0; k < K; ++k) {
        vec3 d = u_delta[k];
        p += b[k] * d;
        J += outerProduct(d, vec3(b[K + 3 * k], b[K + 3 * k + 1], b[K + 3 * k + 2]));
    }
    return J;
}
#endif
#else
mat3 deform_point(int i, inout vec3 p) {
    return mat3(1.0);
}
#endif

vec3 deform_normal(mat3 J, vec3 n) {
    vec3 cn = n.x * cross(J[1], J[2]) + n.y * cross(J[2], J[0]) + n.z * cross(J[0], J[1]);
    float len = length(cn);
    return len > 0.0 ? cn / len : vec3(0.0);
}
