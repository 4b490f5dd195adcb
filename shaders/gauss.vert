// splatdeform: 3D Gaussian splats (3DGS conventions) through the deforming vertex stage.
//
// Per splat: in_position (vec3), the 3D covariance Sigma as in_cov_a = (xx, xy, xz) and
// in_cov_b = (yy, yz, zz), in_color = (0.5 + C0 * f_dc, sigmoid(opacity)); higher SH bands
// (f_rest, channel-major, SH_REST coefficients per channel) from storage buffer 1 at
// gl_VertexID * 3 * SH_REST. The basis comes from deform.glsl (pasted before this file).
//
//   p' = p + B delta C,   Sigma' = deform_covariance(J, Sigma) (covariance.glsl: the
//        ``gaussians.covariance`` mode, J Sigma J^T by default)
//   EWA: t = view p';  Jp = d(window pixels)/dt at t (x/z clamped to 1.3 tan(fov/2), as 3DGS);
//        cov2 = Jp W Sigma' W^T Jp^T + 0.3 I  (W = view rotation, 0.3 px^2 low-pass)
//   colour: SH up to degree 3 at d = normalize(p' - eye); a deformed splat's SH turn with the
//        rotation R of the polar decomposition J = R U, so it is evaluated at R^T d.
//
// The host prepends "#version 330|430 core", "#define DEFORM 0|1", "#define K k",
// "#define SH_DEGREE d", "#define SH_REST ((d+1)^2 - 1)", "#define COVARIANCE m", then
// deform.glsl and covariance.glsl.

in vec3 in_position;
in vec3 in_cov_a;
in vec3 in_cov_b;
in vec4 in_color;
in vec2 in_shape;  // spread and mean of the input splat's log-scales (covariance.glsl)

#if SH_DEGREE > 0
layout(std430, binding = 1) readonly buffer ShRest { float sh_rest[]; };
#endif

uniform mat4 u_view;
uniform mat4 u_proj;
uniform vec2 u_viewport;   // width, height in pixels
uniform vec3 u_eye;        // camera position, relative to the upload origin
uniform float u_near;

out vec4 v_color;    // rgb colour, a opacity (0: culled)
out vec3 v_conic;    // inverse of the 2D covariance (xx, xy, yy), window pixels
out vec2 v_center;   // projected mean, window pixels
out vec2 v_extent;   // half size of the quad (3 sigma along x and y), pixels

const float LOW_PASS = 0.3;
const float SH_C0 = 0.28209479177387814;
const float SH_C1 = 0.4886025119029199;

#if SH_DEGREE > 0
vec3 sh_coeff(int j) {  // j = 1 .. SH_REST
    int base = gl_VertexID * (3 * SH_REST) + (j - 1);
    return vec3(sh_rest[base], sh_rest[base + SH_REST], sh_rest[base + 2 * SH_REST]);
}

vec3 sh_view(vec3 d) {
    float x = d.x, y = d.y, z = d.z;
    vec3 c = -SH_C1 * y * sh_coeff(1) + SH_C1 * z * sh_coeff(2) - SH_C1 * x * sh_coeff(3);
#if SH_DEGREE > 1
    float xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
    c += 1.0925484305920792 * xy * sh_coeff(4)
       - 1.0925484305920792 * yz * sh_coeff(5)
       + 0.31539156525252005 * (2.0 * zz - xx - yy) * sh_coeff(6)
       - 1.0925484305920792 * xz * sh_coeff(7)
       + 0.5462742152960396 * (xx - yy) * sh_coeff(8);
#if SH_DEGREE > 2
    c += -0.5900435899266435 * y * (3.0 * xx - yy) * sh_coeff(9)
       + 2.890611442640554 * xy * z * sh_coeff(10)
       - 0.4570457994644658 * y * (4.0 * zz - xx - yy) * sh_coeff(11)
       + 0.3731763325901154 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh_coeff(12)
       - 0.4570457994644658 * x * (4.0 * zz - xx - yy) * sh_coeff(13)
       + 1.445305721320277 * z * (xx - yy) * sh_coeff(14)
       - 0.5900435899266435 * x * (xx - 3.0 * yy) * sh_coeff(15);
#endif
#endif
    return c;
}
#endif

void main() {
    vec3 p = in_position;
    mat3 sigma = mat3(in_cov_a.x, in_cov_a.y, in_cov_a.z,
                      in_cov_a.y, in_cov_b.x, in_cov_b.y,
                      in_cov_a.z, in_cov_b.y, in_cov_b.z);
#if DEFORM
    mat3 J = deform_point(p);
    sigma = deform_covariance(J, sigma, in_shape);
#endif
    v_color = vec4(0.0);
    v_conic = vec3(0.0);
    v_center = vec2(0.0);
    v_extent = vec2(0.0);
    gl_Position = vec4(0.0, 0.0, 0.0, 1.0);

    vec3 t = (u_view * vec4(p, 1.0)).xyz;
    float z = -t.z;
    if (z <= u_near) {
        return;
    }
    float fx = 0.5 * u_viewport.x * u_proj[0][0];
    float fy = 0.5 * u_viewport.y * u_proj[1][1];
    float limx = 1.3 / u_proj[0][0];
    float limy = 1.3 / u_proj[1][1];
    float tx = clamp(t.x / z, -limx, limx) * z;
    float ty = clamp(t.y / z, -limy, limy) * z;
    // columns of the 3x3 embedding of the 2x3 Jacobian (third row zero)
    mat3 Jp = mat3(fx / z, 0.0, 0.0,
                   0.0, fy / z, 0.0,
                   fx * tx / (z * z), fy * ty / (z * z), 0.0);
    mat3 T = Jp * mat3(u_view);
    mat3 cov = T * sigma * transpose(T);
    float a = cov[0][0] + LOW_PASS;
    float b = cov[0][1];
    float c = cov[1][1] + LOW_PASS;
    float det = a * c - b * b;
    if (!(det > 0.0)) {
        return;
    }
    v_conic = vec3(c, -b, a) / det;
    v_center = vec2(fx * t.x / z + 0.5 * u_viewport.x, fy * t.y / z + 0.5 * u_viewport.y);
    v_extent = 3.0 * sqrt(vec2(a, c));

    vec3 rgb = in_color.rgb;
#if SH_DEGREE > 0
    vec3 d = normalize(p - u_eye);
#if DEFORM
    d = transpose(polar_rotation(J)) * d;  // SH turn with the polar rotation in every mode
#endif
    rgb += sh_view(d);
#endif
    v_color = vec4(max(rgb, 0.0), in_color.a);
}
