/* Per-frame apply of a precomputed deformation basis (the CPU twin of the renderer's vertex
 * shader and of splatdeform.deform.arrays.deform_frame), one work-item per point:
 *
 *     p' = p + sum_k b_k(p) delta_k
 *     J  = I + sum_k delta_k (x) grad b_k(p)
 *     n' = cof(J) n * |n| / |cof(J) n|      (cof(J) n = det(J) J^-T n; 0 stays 0)
 *
 * Compile-time defines: K (basis columns, >= 1), NORMALS (1: also transform normals).
 * Layout (float32, row-major, as the host holds them): pos, nrm, out_p, out_n (n, 3);
 * values (n, K); grads (n, K, 3); delta (K, 3) in constant memory.
 */

__kernel void frame(__global const float *pos, __global const float *nrm,
                    __global const float *values, __global const float *grads,
                    __constant float *delta, __global float *out_p, __global float *out_n,
                    const int n)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    float dx = 0.0f, dy = 0.0f, dz = 0.0f;
#if NORMALS
    float j00 = 1.0f, j01 = 0.0f, j02 = 0.0f;
    float j10 = 0.0f, j11 = 1.0f, j12 = 0.0f;
    float j20 = 0.0f, j21 = 0.0f, j22 = 1.0f;
#endif
#pragma unroll
    for (int k = 0; k < K; k++) {
        const float v = values[K * i + k];
        const float ax = delta[3 * k], ay = delta[3 * k + 1], az = delta[3 * k + 2];
        dx = fma(v, ax, dx);
        dy = fma(v, ay, dy);
        dz = fma(v, az, dz);
#if NORMALS
        const float gx = grads[3 * (K * i + k)];
        const float gy = grads[3 * (K * i + k) + 1];
        const float gz = grads[3 * (K * i + k) + 2];
        j00 = fma(ax, gx, j00); j01 = fma(ax, gy, j01); j02 = fma(ax, gz, j02);
        j10 = fma(ay, gx, j10); j11 = fma(ay, gy, j11); j12 = fma(ay, gz, j12);
        j20 = fma(az, gx, j20); j21 = fma(az, gy, j21); j22 = fma(az, gz, j22);
#endif
    }
    out_p[3 * i] = pos[3 * i] + dx;
    out_p[3 * i + 1] = pos[3 * i + 1] + dy;
    out_p[3 * i + 2] = pos[3 * i + 2] + dz;
#if NORMALS
    const float nx = nrm[3 * i], ny = nrm[3 * i + 1], nz = nrm[3 * i + 2];
    /* cof(J) n = nx (c1 x c2) + ny (c2 x c0) + nz (c0 x c1), columns c_b of J */
    const float ox = nx * (j11 * j22 - j21 * j12) + ny * (j12 * j20 - j22 * j10)
                   + nz * (j10 * j21 - j20 * j11);
    const float oy = nx * (j21 * j02 - j01 * j22) + ny * (j22 * j00 - j02 * j20)
                   + nz * (j20 * j01 - j00 * j21);
    const float oz = nx * (j01 * j12 - j11 * j02) + ny * (j02 * j10 - j12 * j00)
                   + nz * (j00 * j11 - j10 * j01);
    const float len_o = sqrt(ox * ox + oy * oy + oz * oz);
    const float s = len_o > 0.0f ? sqrt(nx * nx + ny * ny + nz * nz) / len_o : 0.0f;
    out_n[3 * i] = ox * s;
    out_n[3 * i + 1] = oy * s;
    out_n[3 * i + 2] = oz * s;
#endif
}
