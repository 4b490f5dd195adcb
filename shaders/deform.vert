// splatdeform: the deforming vertex stage (Botsch & Kobbelt 2005, precomputed RBF basis).
//
// Per point (vertex attributes):
//   in_position (vec3), in_normal (vec3), in_axis_u / in_axis_v (vec3 tangent axes), in_color
//   and, when DEFORM is 1, the basis of k <= 4 control DOFs packed as 16 floats:
//   in_basis (vec4: b_0..b_3) and in_grad0..in_grad3 (vec3: grad b_0 .. grad b_3).
// Uniform u_delta[4]: delta C, one vec3 per control DOF (12 floats for a handle). Unused
// DOFs (k < 4) are zero-padded on the host.
//
// Math (identical to splatdeform/apply.py):
//   p' = p + sum_k b_k delta_k
//   J  = I + sum_k outer(delta_k, grad b_k)
//   n' = normalize(cof(J) n),  cof(J) n = n.x (c1 x c2) + n.y (c2 x c0) + n.z (c0 x c1)
//   u' = J u,  v' = J v
//
// Larger k (curve edits, K > 4): the basis comes from a shader storage buffer instead,
//   layout(std430) readonly buffer Basis { float basis[]; };   // N x (4K) floats
// per vertex K values b_0..b_{K-1} then 3K gradient components (grad b_0, grad b_1, ...),
// read at gl_VertexID * 4K (splats draw points 0..N-1; meshes use indexed draws, where
// gl_VertexID is the vertex index), and delta C as uniform vec3 u_delta[K]; same math, in a loop.
//
// The host prepends "#version 330 core" (or "#version 430 core" when K > 4), "#define DEFORM 0|1"
// and, with DEFORM 1, "#define K <k>" (4 for the attribute path).

in vec3 in_position;
in vec3 in_normal;
in vec3 in_axis_u;
in vec3 in_axis_v;
in vec3 in_color;

#if DEFORM
#ifndef K
#define K 4
#endif
#if K > 4
layout(std430, binding = 0) readonly buffer Basis { float basis[]; };
uniform vec3 u_delta[K];
#else
in vec4 in_basis;
in vec3 in_grad0;
in vec3 in_grad1;
in vec3 in_grad2;
in vec3 in_grad3;
uniform vec3 u_delta[4];
#endif
#endif

uniform mat4 u_view;
uniform mat4 u_proj;

out vec3 v_position;   // deformed position (model units, relative to the upload origin)
out vec3 v_normal;     // deformed unit normal (zero when the input normal is zero)
out vec3 v_axis_u;     // deformed tangent axes
out vec3 v_axis_v;
out vec3 v_color;
out vec3 v_view_pos;   // view-space position (mesh shading)

void main() {
    vec3 p = in_position;
    vec3 n = in_normal;
    vec3 u = in_axis_u;
    vec3 v = in_axis_v;
#if DEFORM
#if K > 4
    int base = gl_VertexID * (4 * K);
    mat3 J = mat3(1.0);
    for (int i = 0; i < K; ++i) {
        vec3 d = u_delta[i];
        p += basis[base + i] * d;
        int g = base + K + 3 * i;
        J += outerProduct(d, vec3(basis[g], basis[g + 1], basis[g + 2]));
    }
#else
    p += in_basis.x * u_delta[0] + in_basis.y * u_delta[1]
       + in_basis.z * u_delta[2] + in_basis.w * u_delta[3];
    mat3 J = mat3(1.0)
           + outerProduct(u_delta[0], in_grad0) + outerProduct(u_delta[1], in_grad1)
           + outerProduct(u_delta[2], in_grad2) + outerProduct(u_delta[3], in_grad3);
#endif
    u = J * u;
    v = J * v;
    vec3 cn = n.x * cross(J[1], J[2]) + n.y * cross(J[2], J[0]) + n.z * cross(J[0], J[1]);
    float len = length(cn);
    n = len > 0.0 ? cn / len : vec3(0.0);
#endif
    v_position = p;
    v_normal = n;
    v_axis_u = u;
    v_axis_v = v;
    v_color = in_color;
    vec4 view_pos = u_view * vec4(p, 1.0);
    v_view_pos = view_pos.xyz;
    gl_Position = u_proj * view_pos;
}
