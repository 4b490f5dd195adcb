// splatdeform: the deformation of the vertex stage (Botsch & Kobbelt 2005, precomputed RBF basis).
// Included by deform.vert and gauss.vert (the host pastes it after the #defines).
//
// With DEFORM 1 the basis of k control DOFs comes either from vertex attributes (K <= 4, 16
// floats: in_basis = b_0..b_3, in_grad0..in_grad3 = grad b_0 .. grad b_3; k < 4 zero-padded)
// or from a shader storage buffer (K > 4: per vertex K values then 3K gradient components,
// read at gl_VertexID * 4K). delta C is uniform vec3 u_delta[max(K, 4)].
//
//   p' = p + sum_k b_k delta_k          J = I + sum_k outer(delta_k, grad b_k)

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

// p: in/out position; returns the Jacobian J of x -> x + d(x) at p.
mat3 deform_point(inout vec3 p) {
#if K > 4
    int base = gl_VertexID * (4 * K);
    mat3 J = mat3(1.0);
    for (int i = 0; i < K; ++i) {
        vec3 d = u_delta[i];
        p += basis[base + i] * d;
        int g = base + K + 3 * i;
        J += outerProduct(d, vec3(basis[g], basis[g + 1], basis[g + 2]));
    }
    return J;
#else
    p += in_basis.x * u_delta[0] + in_basis.y * u_delta[1]
       + in_basis.z * u_delta[2] + in_basis.w * u_delta[3];
    return mat3(1.0)
         + outerProduct(u_delta[0], in_grad0) + outerProduct(u_delta[1], in_grad1)
         + outerProduct(u_delta[2], in_grad2) + outerProduct(u_delta[3], in_grad3);
#endif
}
#endif
