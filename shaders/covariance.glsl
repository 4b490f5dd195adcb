// splatdeform: a deformed Gaussian's covariance, the ``gaussians.covariance`` modes (the numpy
// float64 twin is splatdeform/deform/gaussians.py, held together by tests/test_covariance_modes.py).
//
// COVARIANCE 0 jacobian: Sigma' = J Sigma J^T
//            1 rotation: Sigma' = det(J)^(2/3) R Sigma R^T, R = polar rotation of J;
//                        det J <= 0: Sigma kept (refused)
//            2 limited:  J Sigma J^T with the spread of its log-scales (log largest/smallest axis)
//                        at most that of Sigma + log(ANISOTROPY_GROWTH), pulled towards their
//                        mean (volume kept)
// The host defines COVARIANCE (default 0) and pastes this file after deform.glsl. ``shape`` =
// (spread, mean) of the input splat's log-scales, from float64 on the host: a float32 eigen-solve
// of a thin splat's Sigma (or Sigma') loses its smallest axis, so ``limited`` takes only the two
// largest axes of J Sigma J^T from its eigen-solve and the smallest from the volume,
// sum of log-scales' = 3 mean + log|det J|.

#ifndef COVARIANCE
#define COVARIANCE 0
#endif
const float ANISOTROPY_GROWTH = 2.0;

// R of the polar decomposition J = R U by Newton's iteration R <- (R + R^-T) / 2
mat3 polar_rotation(mat3 J) {
    mat3 R = J;
    for (int i = 0; i < 16; ++i) {
        R = 0.5 * (R + transpose(inverse(R)));
    }
    return R;
}

#if COVARIANCE == 2
// eigenvalues (returned) and eigenvectors (columns of V) of a symmetric 3x3: cyclic Jacobi
vec3 eigen_sym3(mat3 A, out mat3 V) {
    V = mat3(1.0);
    for (int sweep = 0; sweep < 10; ++sweep) {
        for (int k = 0; k < 3; ++k) {
            int p = k == 2 ? 1 : 0;
            int q = k == 0 ? 1 : 2;
            float apq = A[q][p];
            if (abs(apq) <= 1e-30 * (abs(A[p][p]) + abs(A[q][q]))) {
                continue;
            }
            float theta = (A[q][q] - A[p][p]) / (2.0 * apq);
            float t = sign(theta) / (abs(theta) + sqrt(theta * theta + 1.0));
            if (theta == 0.0) {
                t = 1.0;
            }
            float c = inversesqrt(t * t + 1.0);
            float s = t * c;
            mat3 G = mat3(1.0);  // rotation in the (p, q) plane; A <- G^T A G
            G[p][p] = c;
            G[q][q] = c;
            G[q][p] = s;
            G[p][q] = -s;
            A = transpose(G) * A * G;
            V = V * G;
        }
    }
    return vec3(A[0][0], A[1][1], A[2][2]);
}
#endif

mat3 deform_covariance(mat3 J, mat3 sigma, vec2 shape) {
#if COVARIANCE == 1
    float det = determinant(J);
    if (!(det > 0.0)) {
        return sigma;
    }
    mat3 R = polar_rotation(J);
    return pow(det, 2.0 / 3.0) * (R * sigma * transpose(R));
#else
    mat3 out_sigma = J * sigma * transpose(J);
#if COVARIANCE == 2
    mat3 V;
    vec3 lambda = eigen_sym3(out_sigma, V);
    vec3 s = 0.5 * log(max(lambda, vec3(1e-37)));
    int imin = lambda.x <= lambda.y ? (lambda.x <= lambda.z ? 0 : 2)
                                    : (lambda.y <= lambda.z ? 1 : 2);
    float volume = 3.0 * shape.y + log(max(abs(determinant(J)), 1e-37));
    s[imin] = volume - (s.x + s.y + s.z - s[imin]);
    float spread_in = shape.x;
    float spread = max(max(s.x, s.y), s.z) - min(min(s.x, s.y), s.z);
    float allowed = spread_in + log(ANISOTROPY_GROWTH);
    if (spread > allowed) {
        float mean = (s.x + s.y + s.z) / 3.0;
        s = mean + (s - mean) * (allowed / spread);
        out_sigma = V * mat3(exp(2.0 * s.x), 0.0, 0.0, 0.0, exp(2.0 * s.y), 0.0,
                             0.0, 0.0, exp(2.0 * s.z)) * transpose(V);
    }
#endif
    return out_sigma;
#endif
}
