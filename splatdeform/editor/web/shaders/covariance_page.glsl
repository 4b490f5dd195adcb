// splatdeform editor page: shaders/covariance.glsl's modes with one shortcut for ``limited``
// (host pastes this after covariance.glsl). An axis ratio of J Sigma J^T is at most cond(J)
// times Sigma's (sigma_max(J F) <= sigma_max(J) sigma_max(F), likewise the minimum, F = R S), so
// where cond(J) <= ANISOTROPY_GROWTH ``limited`` changes nothing and its eigen-solve is skipped:
// cond(J)^2 from the closed-form eigenvalues of J^T J (a 2% margin for float32).
bool within_growth(mat3 J) {
    mat3 M = transpose(J) * J;
    float q = (M[0][0] + M[1][1] + M[2][2]) / 3.0;
    float p1 = M[0][1] * M[0][1] + M[0][2] * M[0][2] + M[1][2] * M[1][2];
    float p2 = (M[0][0] - q) * (M[0][0] - q) + (M[1][1] - q) * (M[1][1] - q)
             + (M[2][2] - q) * (M[2][2] - q) + 2.0 * p1;
    if (p2 <= 1e-14 * q * q) return true;  // J = s R: every ratio kept
    float p = sqrt(p2 / 6.0);
    float r = clamp(determinant((M - q * mat3(1.0)) / p) * 0.5, -1.0, 1.0);
    float phi = acos(r) / 3.0;
    float largest = q + 2.0 * p * cos(phi);
    float smallest = q + 2.0 * p * cos(phi + 2.0943951023931953);
    return largest <= 0.98 * ANISOTROPY_GROWTH * ANISOTROPY_GROWTH * smallest;
}

mat3 page_covariance(mat3 J, mat3 sigma, vec2 shape) {
#if COVARIANCE == 2
    if (within_growth(J)) return J * sigma * transpose(J);
#endif
    return deform_covariance(J, sigma, shape);
}
