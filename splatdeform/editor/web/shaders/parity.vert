// splatdeform editor page: the deform math of deform.glsl read back by transform feedback, for
// the parity tests against splatdeform/basis/reference.py and splatdeform/deform/gaussians.py
// (host prepends "#define K", "#define COVARIANCE", deform.glsl, shaders/covariance.glsl
// and covariance_page.glsl).
in vec3 position;
in vec3 normal;
in vec3 cov_a;   // xx xy xz
in vec3 cov_b;   // yy yz zz
in vec2 shape;   // spread and mean of the splat's log-scales (covariance.glsl)
out vec3 o_position;
out vec3 o_normal;
out vec3 o_cov_a;
out vec3 o_cov_b;
out vec3 o_r0;
out vec3 o_r1;
out vec3 o_r2;
void main() {
    vec3 p = position;
    mat3 J = deform_point(gl_VertexID, p);
    mat3 s = mat3(cov_a.x, cov_a.y, cov_a.z, cov_a.y, cov_b.x, cov_b.y, cov_a.z, cov_b.y, cov_b.z);
    s = page_covariance(J, s, shape);
    mat3 R = polar_rotation(J);
    o_position = p;
    o_normal = deform_normal(J, normal);
    o_cov_a = vec3(s[0][0], s[1][0], s[2][0]);
    o_cov_b = vec3(s[1][1], s[2][1], s[2][2]);
    o_r0 = R[0];  // columns
    o_r1 = R[1];
    o_r2 = R[2];
    gl_Position = vec4(0.0);
}
