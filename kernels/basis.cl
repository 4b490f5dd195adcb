/* Triharmonic RBF deformation basis (Botsch & Kobbelt 2005), one column per control DOF.
 *
 * For a normalised point p, centers s_j and weights W ((4 + n) x K, rows [1, x, y, z, phi_j]):
 *     b_k(p)      = W[0,k] + p . W[1:4,k] + sum_j |p - s_j|^3 W[4+j,k]
 *     grad b_k(p) = (W[1:4,k] + sum_j 3 |p - s_j| (p - s_j) W[4+j,k]) * inv_scale   (model units)
 *
 * Compile-time defines (all required except where a default is given in basis_real.h):
 *   K          number of basis columns (>= 1); the k loops are fully unrolled
 *   GRADIENTS  1: also write the 3K gradient components; 0: values only
 *   VW         points per work-item (vector width); USE_FP64: see basis_real.h
 *   WG         work-group size (work-items); TILE: centers per local-memory tile
 *   UNROLL_K   1 (default): fully unroll the k loops; 0: keep them rolled (large K)
 *
 * Layout:
 *   pts      (3, stride) real, structure of arrays x | y | z, stride a multiple of VW; every
 *            work-item loads its VW points unguarded, so the host pads to the launched size.
 *   centers  (n_centers, 3 + K) real rows [sx, sy, sz, w_0 .. w_{K-1}]
 *   poly     (4, K) real: the polynomial rows of W
 *   values   (n_points, K) float;  grads (n_points, K, 3) float. Stores are guarded by n_points.
 *
 * Each work-group streams the centers through local memory TILE at a time; each work-item keeps
 * its VW points and 4K accumulators in registers (VW-wide vectors: one SIMD lane per point).
 * Work per point-center pair: 9 + 9K flops with gradients (9 + 2K without), plus one sqrt.
 */
#include "basis_real.h"

/* Unroll the k loops (accumulators in registers) unless the host says K is too large for that
 * (UNROLL_K=0: accumulators in private memory, far shorter build for K in the tens). */
#ifndef UNROLL_K
#define UNROLL_K 1
#endif
#if UNROLL_K
#define SD_UNROLL _Pragma("unroll")
#else
#define SD_UNROLL _Pragma("unroll 1")
#endif

#define CS (3 + K) /* reals per packed center row */

__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void basis(__global const real *restrict pts, const int stride, const int n_points,
           __global const real *restrict centers, const int n_centers,
           __global const real *restrict poly, const real inv_scale,
           __global float *restrict values, __global float *restrict grads)
{
    __local real tile[TILE * CS];
    const int gid = get_global_id(0);
    const int lid = get_local_id(0);

    const realv px = VLOADV(gid, pts);
    const realv py = VLOADV(gid, pts + stride);
    const realv pz = VLOADV(gid, pts + 2 * stride);

    ACC_DECL(val, K);
#if GRADIENTS
    ACC_DECL(gx, K);
    ACC_DECL(gy, K);
    ACC_DECL(gz, K);
#endif
SD_UNROLL
    for (int k = 0; k < K; ++k) {
        ACC_ZERO(val, k);
#if GRADIENTS
        ACC_ZERO(gx, k);
        ACC_ZERO(gy, k);
        ACC_ZERO(gz, k);
#endif
    }

    for (int base = 0; base < n_centers; base += TILE) {
        const int count = min(TILE, n_centers - base);
        barrier(CLK_LOCAL_MEM_FENCE);
        for (int t = lid; t < count * CS; t += WG)
            tile[t] = centers[base * CS + t];
        barrier(CLK_LOCAL_MEM_FENCE);

        for (int j = 0; j < count; ++j) {
            __local const real *c = tile + j * CS;
            const realv dx = px - c[0];
            const realv dy = py - c[1];
            const realv dz = pz - c[2];
            const realv r2 = dx * dx + dy * dy + dz * dz;
            const realv r = sqrt(r2);
            const realv r3 = r2 * r;
SD_UNROLL
            for (int k = 0; k < K; ++k) {
                const real w = c[3 + k];
                ACC_ADD(val, k, r3 * w);
#if GRADIENTS
                const realv rw = r * w;
                ACC_ADD(gx, k, rw * dx);
                ACC_ADD(gy, k, rw * dy);
                ACC_ADD(gz, k, rw * dz);
#endif
            }
        }
    }

    /* Polynomial part, conversion to float, guarded scatter of the VW points. */
    const int i0 = gid * VW;
    const int lanes = min(VW, n_points - i0);
    float out[VW];
SD_UNROLL
    for (int k = 0; k < K; ++k) {
        const realv v = ACC_VALUE(val, k) + poly[k] + px * poly[K + k] + py * poly[2 * K + k]
                        + pz * poly[3 * K + k];
        VSTOREV_F(CONVERT_FLOATV(v), out);
        for (int l = 0; l < lanes; ++l)
            values[(size_t)(i0 + l) * K + k] = out[l];
#if GRADIENTS
        const realv g[3] = {
            (3 * ACC_VALUE(gx, k) + poly[K + k]) * inv_scale,
            (3 * ACC_VALUE(gy, k) + poly[2 * K + k]) * inv_scale,
            (3 * ACC_VALUE(gz, k) + poly[3 * K + k]) * inv_scale,
        };
        for (int a = 0; a < 3; ++a) {
            VSTOREV_F(CONVERT_FLOATV(g[a]), out);
            for (int l = 0; l < lanes; ++l)
                grads[((size_t)(i0 + l) * K + k) * 3 + a] = out[l];
        }
#endif
    }
}
