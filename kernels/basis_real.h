/* Precision and vector-width plumbing for basis.cl.
 *
 * Compile-time defines (set by splatdeform/basis/opencl.py):
 *   USE_FP64  1: accumulate in double (needs cl_khr_fp64); 0: float32 with Kahan compensation.
 *   VW        points per work-item, i.e. the vector width: 1, 2, 4, 8 or 16.
 *
 * Provides: real (scalar), realv (VW-wide vector), floatv, VLOADV, VSTOREV_F, CONVERT_FLOATV,
 * and ACC_DECL / ACC_ZERO / ACC_ADD / ACC_VALUE: an accumulator that is a plain sum in double
 * and a Kahan-compensated sum (value + running compensation) in float.
 */
#ifndef SPLATDEFORM_BASIS_REAL_H
#define SPLATDEFORM_BASIS_REAL_H

#ifndef USE_FP64
#define USE_FP64 1
#endif
#ifndef VW
#define VW 1
#endif

#define SD_CAT_(a, b) a##b
#define SD_CAT(a, b) SD_CAT_(a, b)

#if USE_FP64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#define real double
#else
#define real float
/* Kahan needs the compensation step evaluated as written: no contraction into FMAs. */
#pragma OPENCL FP_CONTRACT OFF
#endif

#if VW == 1
#define realv real
#define floatv float
#define VLOADV(i, p) ((p)[(i)])
#define VSTOREV_F(v, p) (*(p) = (v))
#define CONVERT_FLOATV(x) ((float)(x))
#else
#define realv SD_CAT(real, VW)
#define floatv SD_CAT(float, VW)
#define VLOADV(i, p) SD_CAT(vload, VW)((i), (p))
#define VSTOREV_F(v, p) SD_CAT(vstore, VW)((v), 0, (p))
#define CONVERT_FLOATV(x) SD_CAT(convert_float, VW)(x)
#endif

#if USE_FP64
#define ACC_DECL(name, n) realv name[n]
#define ACC_ZERO(name, k) (name[k] = (realv)(0))
#define ACC_ADD(name, k, term) (name[k] += (term))
#define ACC_VALUE(name, k) (name[k])
#else
/* name[k] is the running sum, name##_c[k] the lost low-order part (Kahan 1965). */
#define ACC_DECL(name, n) realv name[n], name##_c[n]
#define ACC_ZERO(name, k) (name[k] = (realv)(0), name##_c[k] = (realv)(0))
#define ACC_ADD(name, k, term)                                                                  \
    do {                                                                                        \
        const realv acc_y_ = (term) - name##_c[k];                                              \
        const realv acc_t_ = name[k] + acc_y_;                                                  \
        name##_c[k] = (acc_t_ - name[k]) - acc_y_;                                              \
        name[k] = acc_t_;                                                                       \
    } while (0)
#define ACC_VALUE(name, k) (name[k] - name##_c[k])
#endif

#endif /* SPLATDEFORM_BASIS_REAL_H */
