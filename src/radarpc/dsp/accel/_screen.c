/* radarpc.dsp.accel._screen: native CPU kernel for the selection step of the screened beamformer.
 *
 * radarpc.dsp.accel.screened.beamform_peaks_screened computes, for every snapshot j, the bfloat16
 * screen y_j = [Re s^_j | Im s^_j] (2K values, directions in elevation-major column order
 * c = el * n_az + az) with one GEMM. This kernel does everything after that GEMM, one row at a
 * time, reading each row once:
 *
 *   q_jc^2  = Re^2 + Im^2 of column c (bfloat16 widened exactly to float32)
 *   Q_j(az) = max_el q^2_j(el * n_az + az)                     best elevation per azimuth
 *   M_j     = sqrt(max_az Q_j)                                  (double from here on)
 *   need_j  = ((1 - alpha) M_j - 2 beta_j) / (1 + alpha) - 2^-20 M_j
 *             (q_jk >= need_j: k can hold the maximum; the last term covers the float32
 *             rounding of the powers and of need_j^2)
 *   C_j     = {c : q^2_jc >= (float) need_j^2}   (every c when need_j <= 2^-40)
 *   k_j     = argmax_{c in C_j} |B[k(c)] . v_j|,  Ae_j its value (complex64 products summed
 *             in float32 lanes, the modulus in double), ties to the smaller direction k
 *
 * exactly as the torch code in beamform_peaks_screened. A row is flagged "heavy" (left to the
 * whole-grid float32 beamformer) when its candidates span no azimuth or more than max_cand
 * azimuths, or when its screen holds NaN or inf.
 *
 * The per-row power and maxima are plain C loops over independent azimuth lanes, vectorised by
 * the compiler (-O3, no reassociation flag needed); with GCC/Clang on x86 Linux an AVX2 clone of
 * them is chosen at load time (target_clones). The dot products have two kernels, 16 float32
 * partial sums each: "scalar" (plain C, any CPU) and "avx" (intrinsics, x86 with AVX; the
 * compiler's own vectorisation of the scalar one was 5x slower), chosen at run time; with "avx",
 * the subspace screen also runs an AVX2/FMA kernel where the CPU has both. The entry points take
 * raw addresses and a row range and release the GIL, so Python threads can run disjoint row
 * ranges in parallel.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* Define SCREEN_NO_SIMD to build only the portable code (as on MSVC / ARM). */
#if !defined(SCREEN_NO_SIMD) && (defined(__GNUC__) || defined(__clang__)) && (defined(__x86_64__) || defined(__i386__))
#define SCREEN_X86_SIMD 1
#include <immintrin.h>
#define SCREEN_TARGET(t) __attribute__((target(t)))
#else
#define SCREEN_X86_SIMD 0
#endif

/* target_clones needs the loader's ifunc support (glibc on Linux) */
#if SCREEN_X86_SIMD && defined(__linux__) && !defined(SCREEN_NO_CLONES)
#define SCREEN_CLONES __attribute__((target_clones("avx2", "default")))
#else
#define SCREEN_CLONES
#endif

#define LANES 16

/* The candidate threshold's slack and floor; the same values as radarpc.dsp.accel.screened's
 * _SCREEN_SLACK and _SCREEN_TINY_NEED (the tests compare the two selections bit for bit). */
#define SCREEN_SLACK 0x1p-20
#define SCREEN_TINY_NEED 0x1p-40

static inline float bf16_to_f32(uint16_t h)
{
    const uint32_t bits = (uint32_t)h << 16;
    float f;
    memcpy(&f, &bits, sizeof f);
    return f;
}

/* |b . v| for complex64 b, v of length n (interleaved re, im); vs is v with re/im swapped.
 * Re = sum br vr - bi vi (even minus odd lanes of sum b*v), Im = sum br vi + bi vr (sum b*vs).
 * Portable version: 16 explicit partial sums per component. */
static float dot_abs_scalar(const float *b, const float *v, const float *vs, Py_ssize_t n)
{
    float pr[LANES] = {0}, pi[LANES] = {0};
    const Py_ssize_t m = 2 * n, whole = m - m % LANES;
    for (Py_ssize_t i = 0; i < whole; i += LANES)
        for (int l = 0; l < LANES; ++l) {
            pr[l] += b[i + l] * v[i + l];
            pi[l] += b[i + l] * vs[i + l];
        }
    for (Py_ssize_t i = whole; i < m; ++i) {                  /* tail: m is even, lanes keep parity */
        pr[i % LANES] += b[i] * v[i];
        pi[i % LANES] += b[i] * vs[i];
    }
    double re = 0.0, im = 0.0;
    for (int l = 0; l < LANES; l += 2) {
        re += (double)pr[l] - (double)pr[l + 1];
        im += (double)pi[l] + (double)pi[l + 1];
    }
    return (float)sqrt(re * re + im * im);
}

#if SCREEN_X86_SIMD
/* The same with AVX: two 8-float accumulators per component (16 partial sums, as above); the
 * swapped snapshot is formed in registers (vs is not read). */
SCREEN_TARGET("avx") static float dot_abs_avx(const float *b, const float *v, const float *vs, Py_ssize_t n)
{
    (void)vs;
    __m256 r0 = _mm256_setzero_ps(), r1 = _mm256_setzero_ps();
    __m256 i0 = _mm256_setzero_ps(), i1 = _mm256_setzero_ps();
    const Py_ssize_t m = 2 * n, whole = m - m % LANES;
    for (Py_ssize_t i = 0; i < whole; i += LANES) {
        const __m256 b0 = _mm256_loadu_ps(b + i), b1 = _mm256_loadu_ps(b + i + 8);
        const __m256 v0 = _mm256_loadu_ps(v + i), v1 = _mm256_loadu_ps(v + i + 8);
        r0 = _mm256_add_ps(r0, _mm256_mul_ps(b0, v0));
        r1 = _mm256_add_ps(r1, _mm256_mul_ps(b1, v1));
        i0 = _mm256_add_ps(i0, _mm256_mul_ps(b0, _mm256_permute_ps(v0, 0xB1)));   /* (vi, vr) pairs */
        i1 = _mm256_add_ps(i1, _mm256_mul_ps(b1, _mm256_permute_ps(v1, 0xB1)));
    }
    float pr[LANES], pi[LANES];
    _mm256_storeu_ps(pr, r0);
    _mm256_storeu_ps(pr + 8, r1);
    _mm256_storeu_ps(pi, i0);
    _mm256_storeu_ps(pi + 8, i1);
    for (Py_ssize_t i = whole; i < m; i += 2) {               /* tail: whole complex values */
        pr[i % LANES] += b[i] * v[i];
        pr[i % LANES + 1] += b[i + 1] * v[i + 1];
        pi[i % LANES] += b[i] * v[i + 1];
        pi[i % LANES + 1] += b[i + 1] * v[i];
    }
    double re = 0.0, im = 0.0;
    for (int l = 0; l < LANES; l += 2) {
        re += (double)pr[l] - (double)pr[l + 1];
        im += (double)pi[l] + (double)pi[l + 1];
    }
    return (float)sqrt(re * re + im * im);
}
#endif

typedef float (*dot_abs_fn)(const float *, const float *, const float *, Py_ssize_t);

enum { KERNEL_AUTO = 0, KERNEL_SCALAR = 1, KERNEL_AVX = 2 };
static const char *const kernel_names[] = {"auto", "scalar", "avx"};

static int kernel_on_cpu(int kernel)
{
    switch (kernel) {
    case KERNEL_SCALAR:
        return 1;
#if SCREEN_X86_SIMD
    case KERNEL_AVX:
        return __builtin_cpu_supports("avx");
#endif
    default:
        return 0;
    }
}

/* The kernel named 'auto', 'scalar' or 'avx' that runs here, or -1 with a ValueError set. */
static int kernel_by_name(const char *name)
{
    int kernel = -1;
    for (int k = 0; k < (int)(sizeof(kernel_names) / sizeof(kernel_names[0])); ++k)
        if (strcmp(name, kernel_names[k]) == 0)
            kernel = k;
    if (kernel == KERNEL_AUTO)
        kernel = kernel_on_cpu(KERNEL_AVX) ? KERNEL_AVX : KERNEL_SCALAR;
    if (kernel < 0 || !kernel_on_cpu(kernel)) {
        PyErr_Format(PyExc_ValueError, "kernel '%s' is not one of 'auto', 'scalar', 'avx' or cannot run on "
                     "this build/CPU", name);
        return -1;
    }
    return kernel;
}

static dot_abs_fn kernel_dot(int kernel)
{
#if SCREEN_X86_SIMD
    if (kernel == KERNEL_AVX)
        return dot_abs_avx;
#endif
    (void)kernel;
    return dot_abs_scalar;
}

/* Work arrays of one call: per-azimuth maxima and finiteness checks, one swapped snapshot. */
typedef struct {
    float *q_az, *check, *vs;
} scratch_t;

SCREEN_CLONES
static void select_rows(const uint16_t *y, Py_ssize_t y_stride, const float *v, const float *rows,
                        const float *beta, Py_ssize_t n_rows, Py_ssize_t n_az, Py_ssize_t n_el,
                        Py_ssize_t n_virtual, double alpha, Py_ssize_t max_cand, int64_t *index,
                        float *amplitude, uint8_t *heavy, dot_abs_fn dot_abs, scratch_t *w)
{
    const Py_ssize_t k_dir = n_az * n_el;
    float *q_az = w->q_az, *check = w->check, *vs = w->vs;
    for (Py_ssize_t j = 0; j < n_rows; ++j) {
        const uint16_t *yr = y + y_stride * j, *yi = yr + k_dir;
        /* Q(az) = max over elevation of q^2; check(az) becomes NaN if any q^2 is NaN or inf */
        for (Py_ssize_t az = 0; az < n_az; ++az) {
            const float re = bf16_to_f32(yr[az]), im = bf16_to_f32(yi[az]);
            const float q = re * re + im * im;
            q_az[az] = q;
            check[az] = q * 0.0f;
        }
        for (Py_ssize_t el = 1; el < n_el; ++el) {
            const uint16_t *er = yr + el * n_az, *ei = yi + el * n_az;
            for (Py_ssize_t az = 0; az < n_az; ++az) {
                const float re = bf16_to_f32(er[az]), im = bf16_to_f32(ei[az]);
                const float q = re * re + im * im;
                q_az[az] = q > q_az[az] ? q : q_az[az];
                check[az] = check[az] + q * 0.0f;
            }
        }
        float q_max = 0.0f, bad = 0.0f;
        for (Py_ssize_t az = 0; az < n_az; ++az) {
            q_max = q_az[az] > q_max ? q_az[az] : q_max;
            bad = bad + check[az];
        }
        const float bj = beta[j];
        const double m_j = sqrt((double)q_max);
        const double need = ((1.0 - alpha) * m_j - 2.0 * (double)bj) / (1.0 + alpha) - SCREEN_SLACK * m_j;
        const float need2 = need > SCREEN_TINY_NEED ? (float)(need * need) : -1.0f;
        Py_ssize_t n_cand = 0;
        for (Py_ssize_t az = 0; az < n_az; ++az)
            n_cand += q_az[az] >= need2;
        if (bad != 0.0f || !isfinite(bj) || n_cand == 0 || n_cand > max_cand) {   /* bad is 0 or NaN */
            heavy[j] = 1;
            index[j] = -1;
            amplitude[j] = 0.0f;
            continue;
        }
        heavy[j] = 0;
        const float *vj = v + 2 * n_virtual * j;
        for (Py_ssize_t i = 0; i < n_virtual && dot_abs == dot_abs_scalar; ++i) {   /* AVX swaps in registers */
            vs[2 * i] = vj[2 * i + 1];
            vs[2 * i + 1] = vj[2 * i];
        }
        float best = -1.0f;
        int64_t best_k = -1;
        for (Py_ssize_t az = 0; az < n_az; ++az) {             /* k = az n_el + el ascending */
            if (!(q_az[az] >= need2))
                continue;
            for (Py_ssize_t el = 0; el < n_el; ++el) {
                const Py_ssize_t c = el * n_az + az;
                const float re = bf16_to_f32(yr[c]), im = bf16_to_f32(yi[c]);
                if (!(re * re + im * im >= need2))
                    continue;
                const Py_ssize_t k = az * n_el + el;
                const float s = dot_abs(rows + 2 * n_virtual * k, vj, vs, n_virtual);
                if (s > best) {                                /* strict: ties keep the smaller k */
                    best = s;
                    best_k = k;
                }
            }
        }
        index[j] = best_k;
        amplitude[j] = best;
    }
}

/* ---------------------------------------------------------------- certified decision --- */
/* For every point j and its candidate directions k (CSR: kidx[ptr[j] .. ptr[j+1])), evaluate
 * |B[k] . v_j| in double and pick the largest, ties to the smaller elevation-major column
 * c = el n_az + az (the exact beamformer's first maximum). float32 x float32 products are exact
 * in double; the 2N-term sums of Re and Im are off by at most gamma_2N S (S = sum (|br| + |bi|)
 * (|vr| + |vi|), any summation order), so |f - |s|| <= beta = 1.5 gamma_(2N+2) S + 2^-50 f with f
 * the computed modulus. A point is flagged ambiguous when another candidate's interval
 * [f - beta, f + beta] reaches the best one's (beta = 0 means S = 0: the value is exactly 0, and
 * equal exact values are a true tie, settled by the column order). */
#define F64_LANES 4
SCREEN_CLONES
static double dot_abs_f64(const float *b, const float *v, Py_ssize_t n, double *bound)
{
    /* F64_LANES independent partial sums per quantity, so the compiler vectorises without
     * reassociating (the bound holds for any summation order) */
    double re0[F64_LANES] = {0}, re1[F64_LANES] = {0}, im0[F64_LANES] = {0}, im1[F64_LANES] = {0},
           s1[F64_LANES] = {0};
    const Py_ssize_t whole = n - n % F64_LANES;
    for (Py_ssize_t i = 0; i < whole; i += F64_LANES)
        for (int l = 0; l < F64_LANES; ++l) {
            const double br = b[2 * (i + l)], bi = b[2 * (i + l) + 1], vr = v[2 * (i + l)], vi = v[2 * (i + l) + 1];
            re0[l] += br * vr;
            re1[l] += bi * vi;
            im0[l] += br * vi;
            im1[l] += bi * vr;
            s1[l] += (fabs(br) + fabs(bi)) * (fabs(vr) + fabs(vi));
        }
    for (Py_ssize_t i = whole; i < n; ++i) {
        const double br = b[2 * i], bi = b[2 * i + 1], vr = v[2 * i], vi = v[2 * i + 1];
        re0[0] += br * vr;
        re1[0] += bi * vi;
        im0[0] += br * vi;
        im1[0] += bi * vr;
        s1[0] += (fabs(br) + fabs(bi)) * (fabs(vr) + fabs(vi));
    }
    double re = 0.0, im = 0.0, s = 0.0;
    for (int l = 0; l < F64_LANES; ++l) {
        re += re0[l] - re1[l];
        im += im0[l] + im1[l];
        s += s1[l];
    }
    const double f = sqrt(re * re + im * im);
    const double m = (double)(2 * n + 2) * 0x1p-53;
    *bound = 1.5 * (m / (1.0 - m)) * s * (1.0 + 0x1p-40) + 0x1p-50 * f;
    return f;
}

static void certify_points(const float *v, const float *rows, Py_ssize_t n_virtual, const int64_t *ptr,
                           const int64_t *kidx, Py_ssize_t n_points, Py_ssize_t n_az, Py_ssize_t n_el,
                           int64_t *index, float *amplitude, uint8_t *ambiguous, double *work)
{
    for (Py_ssize_t j = 0; j < n_points; ++j) {
        const int64_t lo = ptr[j], hi = ptr[j + 1];
        const float *vj = v + 2 * n_virtual * j;
        int64_t best_k = -1, best_c = -1;
        double best = -1.0, best_b = 0.0;
        for (int64_t p = lo; p < hi; ++p) {
            const int64_t k = kidx[p], c = (k % n_el) * n_az + k / n_el;
            double b;
            const double f = dot_abs_f64(rows + 2 * n_virtual * k, vj, n_virtual, &b);
            work[2 * (p - lo)] = f;
            work[2 * (p - lo) + 1] = b;
            if (f > best || (f == best && c < best_c)) {
                best = f;
                best_b = b;
                best_k = k;
                best_c = c;
            }
        }
        uint8_t amb = best != best;                              /* NaN: left to the caller */
        for (int64_t p = lo; p < hi && !amb; ++p) {
            if (kidx[p] == best_k)
                continue;
            const double f = work[2 * (p - lo)], b = work[2 * (p - lo) + 1];
            if ((b > 0.0 || best_b > 0.0) && f + b >= best - best_b)
                amb = 1;
        }
        index[j] = best_k;
        amplitude[j] = (float)best;
        ambiguous[j] = amb;
    }
}

/* ---------------------------------------------------------------- subspace screen ------ */
/* The selection of radarpc.dsp.accel.subspace, fused with its second product: for every point j,
 * y = [Re y_g (r) | Im y_g (r)] per group g (row j of the float32 GEMM x w1), the screen of the
 * group's M directions k = g M + t is z^_k = sum_t c_kt y_t (float32, 2r terms per component:
 * the same gamma_2r bound as any order), coef[g][0][t][.] = Re c_.t, coef[g][1][t][.] = Im c_.t.
 * With |s_k - z^_k| <= e_k = resid_k R_g + slack_k xn_j (R_g >= ||(I - P_g) v||, below) and
 * a_k = |z^_k| (q_k = a_k^2 in double: products of float32 values are exact), L = a_b - e_b for
 * b = argmax q in a screened group is a lower bound of max_k |s_k| (the largest over the groups
 * is kept), and k is a candidate when a_k + e_k >= L, tested as q_k >= (L - e_k)^2 (or
 * L - e_k <= 0); each a_b - e_b is lowered by 2^-40 (a_b + e_max xn), far more than the double
 * rounding of the test. The candidates are decided as in certify_points. More than max_cand
 * candidates or a non-finite screen or norm -> heavy (index -1; the caller runs the exact
 * beamformer). */
/* Candidates up to which a point goes straight to the float64 decision. */
#define REFINE_MIN 8

typedef void (*group_fn)(const float *, const float *, Py_ssize_t, Py_ssize_t, Py_ssize_t, float *, float *, double *);

typedef struct {
    const float *coef, *resid, *slack, *cmax, *rmax, *smax;
    const double *gram_max;
    double y_error, e_max;                  /* e_max: max_k (resid_k + slack_k), so e_k <= e_max xn */
    Py_ssize_t n_groups, rank, m_rows, k_dir;
    group_fn group;                         /* the screen kernel of one group */
} subspace_t;

SCREEN_CLONES
static void subspace_group(const float *yg, const float *cg, Py_ssize_t rank, Py_ssize_t m_rows, Py_ssize_t m,
                           float *re, float *im, double *q)
{
    for (Py_ssize_t t = 0; t < m; ++t) {
        re[t] = 0.0f;
        im[t] = 0.0f;
    }
    for (Py_ssize_t u = 0; u < rank; ++u) {
        const float yr = yg[u], yi = yg[rank + u];
        const float *cr = cg + u * m_rows, *ci = cg + (rank + u) * m_rows;
        for (Py_ssize_t t = 0; t < m; ++t) {
            re[t] = re[t] + cr[t] * yr;
            re[t] = re[t] - ci[t] * yi;
            im[t] = im[t] + ci[t] * yr;
            im[t] = im[t] + cr[t] * yi;
        }
    }
    for (Py_ssize_t t = 0; t < m; ++t)
        q[t] = (double)re[t] * re[t] + (double)im[t] * im[t];
}

#if SCREEN_X86_SIMD
/* The same with AVX2 and FMA: 32 directions at a time, their sums in eight registers over the rank
 * (each coefficient is read once per point); fused products only lower the rounding, and the
 * gamma_2r bound holds for any order. The tail of fewer than 8 directions runs the portable loop. */
SCREEN_TARGET("avx2,fma")
static void subspace_group_fma(const float *yg, const float *cg, Py_ssize_t rank, Py_ssize_t m_rows, Py_ssize_t m,
                               float *re, float *im, double *q)
{
    Py_ssize_t t0 = 0;
    for (; t0 + 32 <= m; t0 += 32) {
        __m256 r0 = _mm256_setzero_ps(), r1 = r0, r2 = r0, r3 = r0, i0 = r0, i1 = r0, i2 = r0, i3 = r0;
        for (Py_ssize_t u = 0; u < rank; ++u) {
            const __m256 yr = _mm256_broadcast_ss(yg + u), yi = _mm256_broadcast_ss(yg + rank + u);
            const float *cr = cg + u * m_rows + t0, *ci = cg + (rank + u) * m_rows + t0;
            const __m256 a0 = _mm256_loadu_ps(cr), a1 = _mm256_loadu_ps(cr + 8), a2 = _mm256_loadu_ps(cr + 16),
                         a3 = _mm256_loadu_ps(cr + 24);
            const __m256 b0 = _mm256_loadu_ps(ci), b1 = _mm256_loadu_ps(ci + 8), b2 = _mm256_loadu_ps(ci + 16),
                         b3 = _mm256_loadu_ps(ci + 24);
            r0 = _mm256_fnmadd_ps(b0, yi, _mm256_fmadd_ps(a0, yr, r0));
            r1 = _mm256_fnmadd_ps(b1, yi, _mm256_fmadd_ps(a1, yr, r1));
            r2 = _mm256_fnmadd_ps(b2, yi, _mm256_fmadd_ps(a2, yr, r2));
            r3 = _mm256_fnmadd_ps(b3, yi, _mm256_fmadd_ps(a3, yr, r3));
            i0 = _mm256_fmadd_ps(a0, yi, _mm256_fmadd_ps(b0, yr, i0));
            i1 = _mm256_fmadd_ps(a1, yi, _mm256_fmadd_ps(b1, yr, i1));
            i2 = _mm256_fmadd_ps(a2, yi, _mm256_fmadd_ps(b2, yr, i2));
            i3 = _mm256_fmadd_ps(a3, yi, _mm256_fmadd_ps(b3, yr, i3));
        }
        _mm256_storeu_ps(re + t0, r0);
        _mm256_storeu_ps(re + t0 + 8, r1);
        _mm256_storeu_ps(re + t0 + 16, r2);
        _mm256_storeu_ps(re + t0 + 24, r3);
        _mm256_storeu_ps(im + t0, i0);
        _mm256_storeu_ps(im + t0 + 8, i1);
        _mm256_storeu_ps(im + t0 + 16, i2);
        _mm256_storeu_ps(im + t0 + 24, i3);
    }
    for (; t0 + 8 <= m; t0 += 8) {
        __m256 r0 = _mm256_setzero_ps(), i0 = r0;
        for (Py_ssize_t u = 0; u < rank; ++u) {
            const __m256 yr = _mm256_broadcast_ss(yg + u), yi = _mm256_broadcast_ss(yg + rank + u);
            const __m256 a0 = _mm256_loadu_ps(cg + u * m_rows + t0), b0 = _mm256_loadu_ps(cg + (rank + u) * m_rows + t0);
            r0 = _mm256_fnmadd_ps(b0, yi, _mm256_fmadd_ps(a0, yr, r0));
            i0 = _mm256_fmadd_ps(a0, yi, _mm256_fmadd_ps(b0, yr, i0));
        }
        _mm256_storeu_ps(re + t0, r0);
        _mm256_storeu_ps(im + t0, i0);
    }
    if (t0 < m)
        subspace_group(yg, cg + t0, rank, m_rows, m - t0, re + t0, im + t0, q + t0);
    for (Py_ssize_t t = 0; t < t0; ++t)            /* q in double: exact products, one rounding */
        q[t] = (double)re[t] * re[t] + (double)im[t] * im[t];
}
#endif

/* The screen kernel that goes with a dot kernel: the AVX2/FMA one with 'avx' where the CPU has them. */
static group_fn kernel_group(int kernel)
{
#if SCREEN_X86_SIMD
    if (kernel == KERNEL_AVX && __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma"))
        return subspace_group_fma;
#endif
    (void)kernel;
    return subspace_group;
}

/* sum of squares of n float32 values in double, 8 independent partial sums (vectorised; the
 * products are exact, the sum within n 2^-53 relative in any order) */
SCREEN_CLONES
static double sum_squares(const float *a, Py_ssize_t n)
{
    double acc[8] = {0};
    const Py_ssize_t whole = n - n % 8;
    for (Py_ssize_t i = 0; i < whole; i += 8)
        for (int l = 0; l < 8; ++l)
            acc[l] += (double)a[i + l] * a[i + l];
    for (Py_ssize_t i = whole; i < n; ++i)
        acc[i - whole] += (double)a[i] * a[i];
    double s = 0.0;
    for (int l = 0; l < 8; ++l)
        s += acc[l];
    return s;
}

/* The largest of q[0 .. m) (the first one on ties) and whether every value is finite; 8 lanes. */
SCREEN_CLONES
static Py_ssize_t argmax_finite(const double *q, Py_ssize_t m, int *finite)
{
    double mx[8], chk[8] = {0};
    for (int l = 0; l < 8; ++l)
        mx[l] = -INFINITY;
    const Py_ssize_t whole = m - m % 8;
    for (Py_ssize_t i = 0; i < whole; i += 8)
        for (int l = 0; l < 8; ++l) {
            mx[l] = q[i + l] > mx[l] ? q[i + l] : mx[l];
            chk[l] += q[i + l] * 0.0;
        }
    for (Py_ssize_t i = whole; i < m; ++i) {
        mx[0] = q[i] > mx[0] ? q[i] : mx[0];
        chk[0] += q[i] * 0.0;
    }
    double best = -INFINITY, bad = 0.0;
    for (int l = 0; l < 8; ++l) {
        best = mx[l] > best ? mx[l] : best;
        bad += chk[l];
    }
    *finite = bad == 0.0;                  /* bad is 0 or NaN */
    Py_ssize_t t = 0;
    while (t < m - 1 && !(q[t] == best))
        ++t;
    return t;
}

/* Per group: the residual bound R_g = sqrt(||v||^2 - max(0, ||y^_g|| - y_error ||v||)^2 / gram_max_g)
 * (||P_g v|| >= ||Q_g v|| / sqrt(lambda_max), ||Q_g v|| >= ||y^_g|| - y_error ||v||); ||v||^2 and
 * ||y^_g||^2 are summed in double from float32 values (products exact, relative errors of the sums
 * below 2N 2^-53 and 2r 2^-53, and of the square roots 2^-53: covered by the (2N + 2) 2^-52 and
 * (2r + 2) 2^-52 factors), so R_g >= ||(I - P_g) v|| and, up to a few ulps, R_g <= ||v|| <= xn.
 * Group pruning: |z^_k| <= ||c_k|| ||y_g|| + |z^_k - c_k . y_g| <= cmax_g ||y_g|| + e_k (the second
 * product's rounding is part of the slack), so no direction of group g can be a candidate
 * (a_k + e_k >= L) when ub_g = cmax_g ||y_g|| + 2 (rmax_g R_g + smax_g xn) < L. The group with the
 * largest ub is screened first; every other group only if its ub reaches the lower bound L of the
 * groups screened so far (L is their largest, so a skipped group stays below the final L). */
static Py_ssize_t subspace_points_one(const float *y, const float *vj, Py_ssize_t n_virtual, const subspace_t *tb,
                                      double x, Py_ssize_t max_cand, double *q, float *re, float *im, double *ub,
                                      double *rg, uint8_t *done, int64_t *cand, int *finite)
{
    const Py_ssize_t n_groups = tb->n_groups, rank = tb->rank, m_rows = tb->m_rows, k_dir = tb->k_dir;
    const double vn2 = sum_squares(vj, 2 * n_virtual) * (1.0 + (double)(2 * n_virtual + 2) * 0x1p-52);
    const double vn = sqrt(vn2) * (1.0 + 0x1p-40), y_err = tb->y_error * vn;
    double bad = vn2 * 0.0, low = -INFINITY;
    Py_ssize_t g0 = 0;
    for (Py_ssize_t g = 0; g < n_groups; ++g) {
        const double ny = sqrt(sum_squares(y + 2 * rank * g, 2 * rank));
        double lo = ny * (1.0 - (double)(2 * rank + 2) * 0x1p-52) - y_err;
        lo = lo > 0.0 ? lo : 0.0;
        const double r2 = vn2 - lo * lo / tb->gram_max[g];
        rg[g] = sqrt(r2 > 0.0 ? r2 : 0.0) * (1.0 + 0x1p-40);
        ub[g] = ((double)tb->cmax[g] * ny + 2.0 * ((double)tb->rmax[g] * rg[g] + (double)tb->smax[g] * x))
                * (1.0 + 0x1p-20);
        bad += ub[g] * 0.0;
        done[g] = 0;
        if (ub[g] > ub[g0])
            g0 = g;
    }
    if (bad != 0.0 || !isfinite(x)) {
        *finite = 0;
        return 0;
    }
    const double e_round = 0x1p-40 * tb->e_max * x;
    for (Py_ssize_t step = -1; step < n_groups; ++step) {
        const Py_ssize_t g = step < 0 ? g0 : step;
        if (done[g] || ub[g] < low)
            continue;
        const Py_ssize_t k0 = g * m_rows, m = k0 + m_rows <= k_dir ? m_rows : k_dir - k0;
        tb->group(y + 2 * rank * g, tb->coef + 2 * rank * m_rows * g, rank, m_rows, m, re, im, q + k0);
        done[g] = 1;
        int ok;
        const Py_ssize_t t = argmax_finite(q + k0, m, &ok);
        if (!ok) {
            *finite = 0;
            return 0;
        }
        /* L = a_b - e_b of the group's largest a_b, lowered by 2^-40 (a_b + e_max xn) for the double
         * rounding of the tests; the largest so far is kept */
        const double ab = sqrt(q[k0 + t]);
        const double lb = ab * (1.0 - 0x1p-50 - 0x1p-40) - ((double)tb->resid[k0 + t] * rg[g]
                                                            + (double)tb->slack[k0 + t] * x) - e_round;
        if (lb > low)
            low = lb;
    }
    *finite = 1;
    Py_ssize_t n_cand = 0;
    for (Py_ssize_t g = 0; g < n_groups && n_cand <= max_cand; ++g) {
        if (!done[g])
            continue;
        const Py_ssize_t k0 = g * m_rows, k1 = k0 + m_rows <= k_dir ? k0 + m_rows : k_dir;
        const double r = rg[g];
        /* e_k <= e_g = rmax_g R_g + smax_g xn (rounding is monotone), so q_k < (L - e_g)^2 with
         * L - e_g > 0 rules k out before its own bound is formed */
        const double thr = low - ((double)tb->rmax[g] * r + (double)tb->smax[g] * x);
        const double thr2 = thr > 0.0 ? thr * thr : -1.0;
        for (Py_ssize_t k = k0; k < k1 && n_cand <= max_cand; ++k) {
            if (!(q[k] >= thr2))
                continue;
            const double rhs = low - ((double)tb->resid[k] * r + (double)tb->slack[k] * x);
            if (rhs <= 0.0 || q[k] >= rhs * rhs)
                cand[n_cand++] = k;
        }
    }
    if (n_cand <= REFINE_MIN || n_cand > max_cand)
        return n_cand;
    /* Many candidates: L becomes max_k (a_k - e_k) over them. The k that maximises a_k - e_k over
     * the screened directions is among them (a_k + e_k >= a_k - e_k >= L), so this is the maximum
     * over every screened direction: a largest a_b with a large e_b no longer sets a low L. */
    double best = low;
    for (Py_ssize_t p = 0; p < n_cand; ++p) {
        const int64_t k = cand[p];
        const double e = (double)tb->resid[k] * rg[k / m_rows] + (double)tb->slack[k] * x;
        const double lb = sqrt(q[k]) * (1.0 - 0x1p-50 - 0x1p-40) - e - e_round;
        best = lb > best ? lb : best;
    }
    Py_ssize_t kept = 0;
    for (Py_ssize_t p = 0; p < n_cand; ++p) {
        const int64_t k = cand[p];
        const double rhs = best - ((double)tb->resid[k] * rg[k / m_rows] + (double)tb->slack[k] * x);
        if (rhs <= 0.0 || q[k] >= rhs * rhs)
            cand[kept++] = k;
    }
    return kept;
}

/* Many candidates (flat, noise-like spectra): a float32 pass first. f_k = |B[k] . v| from the
 * float32 dot kernel; each of Re and Im is a sum of 2N float32 products in any order, so it is
 * within gamma_(2N+1) sum (|br| + |bi|)(|vr| + |vi|) <= gamma_(2N+1) 2 ||B[k]|| ||v|| of the exact
 * value, and |f_k - |s_k|| <= e = 2 sqrt(2) gamma_(2N+2) R ||v|| + 2^-22 f_k (R = max_k ||B[k]||;
 * the last term covers the modulus in double and its float32 rounding). Only candidates with
 * f_k + e_k >= f_b - e_b (b the largest f) can hold the maximum; they go to certify_points. */
static Py_ssize_t refine_f32(const float *vj, const float *rows, Py_ssize_t n_virtual, int64_t *cand,
                             Py_ssize_t n_cand, double row_norm_max, double vnorm, dot_abs_fn dot, float *vs,
                             double *work)
{
    const double m = (double)(2 * n_virtual + 2) * 0x1p-24;
    const double base = 2.0 * sqrt(2.0) * (m / (1.0 - m)) * row_norm_max * vnorm * (1.0 + 0x1p-20);
    for (Py_ssize_t i = 0; i < n_virtual; ++i) {
        vs[2 * i] = vj[2 * i + 1];
        vs[2 * i + 1] = vj[2 * i];
    }
    double best = -1.0;
    for (Py_ssize_t p = 0; p < n_cand; ++p) {
        work[p] = dot(rows + 2 * n_virtual * cand[p], vj, vs, n_virtual);
        best = work[p] > best ? work[p] : best;
    }
    if (!(best >= 0.0) || !isfinite(best) || !isfinite(base))   /* NaN or overflow: keep them all */
        return n_cand;
    const double low = best - (base + 0x1p-22 * best);
    Py_ssize_t kept = 0;
    for (Py_ssize_t p = 0; p < n_cand; ++p)
        if (!(work[p] + base + 0x1p-22 * work[p] < low))      /* a NaN value is kept */
            cand[kept++] = cand[p];                           /* ascending order is kept */
    return kept;
}

static void subspace_points(const float *y, Py_ssize_t y_stride, const subspace_t *tb, const float *xn,
                            Py_ssize_t n_points, const float *v, const float *rows, Py_ssize_t n_virtual,
                            Py_ssize_t n_az, Py_ssize_t n_el, Py_ssize_t max_cand, double row_norm_max,
                            dot_abs_fn dot, int64_t *index, float *amplitude, uint8_t *ambiguous, uint8_t *heavy,
                            double *q, float *re, float *im, double *ub,
                            double *rg, uint8_t *done, int64_t *cand, float *vs, double *work)
{
    for (Py_ssize_t j = 0; j < n_points; ++j) {
        int finite;
        const float *vj = v + 2 * n_virtual * j;
        Py_ssize_t n_cand = subspace_points_one(y + y_stride * j, vj, n_virtual, tb, (double)xn[j], max_cand, q, re,
                                                im, ub, rg, done, cand, &finite);
        index[j] = -1;
        amplitude[j] = 0.0f;
        ambiguous[j] = 0;
        if (!finite || n_cand == 0 || n_cand > max_cand) {
            heavy[j] = 1;
            continue;
        }
        heavy[j] = 0;
        if (n_cand > REFINE_MIN)
            n_cand = refine_f32(vj, rows, n_virtual, cand, n_cand, row_norm_max, (double)xn[j], dot, vs, work);
        const int64_t ptr[2] = {0, (int64_t)n_cand};
        certify_points(vj, rows, n_virtual, ptr, cand, 1, n_az, n_el, index + j, amplitude + j, ambiguous + j,
                       work);
    }
}

PyDoc_STRVAR(subspace_select_doc,
"subspace_select(y, y_stride, coef, resid, slack, cmax, rmax, smax, gram_max, y_error, e_max, xn,\n"
"                n_groups, rank, m_rows, k_dir, n_points, v, rows, n_virtual, n_az, n_el, max_cand,\n"
"                row_norm_max, index, amplitude, ambiguous, heavy, kernel='auto')\n"
"--\n\n"
"Screen, selection and certified decision of the subspace beamformer for n_points points (see\n"
"the module source). Addresses: y float32 rows of y_stride elements (G 2 rank used); coef\n"
"float32 (G, 2, rank, m_rows); resid, slack float32 (k_dir,) (e_k = resid_k R_g + slack_k xn);\n"
"cmax, rmax, smax float32 (G,) (per group the largest coefficient norm, resid and slack);\n"
"gram_max float64 (G,); xn float32 (n_points,) (snapshot norms, rounded up); v complex64\n"
"(n_points, n_virtual); rows complex64 (k_dir, n_virtual); y_error: ||y^_g - Q_g v|| <=\n"
"y_error ||v||; e_max >= max_k (resid_k + slack_k); row_norm_max >= max_k ||rows[k]||; kernel\n"
"'auto', 'scalar' or 'avx' (the float32 dot of points with many candidates and, with AVX2 and\n"
"FMA, the screen). Outputs index int64, amplitude float32, ambiguous uint8, heavy uint8 (heavy\n"
"points get index -1). The GIL is released.");

static PyObject *py_subspace_select(PyObject *self, PyObject *args)
{
    unsigned long long y, coef, resid, slack, cmax, rmax, smax, gram_max, xn, v, rows, index, amplitude, ambiguous,
        heavy;
    Py_ssize_t y_stride, n_groups, rank, m_rows, k_dir, n_points, n_virtual, n_az, n_el, max_cand;
    double y_error, e_max, row_norm_max;
    const char *name = "auto";
    (void)self;
    if (!PyArg_ParseTuple(args, "KnKKKKKKKddKnnnnnKKnnnndKKKK|s", &y, &y_stride, &coef, &resid, &slack, &cmax, &rmax,
                          &smax, &gram_max, &y_error, &e_max, &xn, &n_groups, &rank, &m_rows, &k_dir, &n_points, &v,
                          &rows, &n_virtual, &n_az, &n_el, &max_cand, &row_norm_max, &index, &amplitude, &ambiguous,
                          &heavy, &name))
        return NULL;
    const int kernel = kernel_by_name(name);
    if (kernel < 0)
        return NULL;
    if (n_points < 0 || n_groups < 1 || rank < 1 || m_rows < 1 || k_dir < 1 || k_dir > n_groups * m_rows
        || n_virtual < 1 || n_az * n_el != k_dir || max_cand < 1 || y_stride < 2 * rank * n_groups
        || !(y_error >= 0.0) || !(e_max >= 0.0)) {
        PyErr_SetString(PyExc_ValueError, "subspace_select: inconsistent sizes or bounds");
        return NULL;
    }
    if (n_points == 0)
        Py_RETURN_NONE;
    if (max_cand > k_dir)
        max_cand = k_dir;
    const subspace_t tb = {(const float *)(uintptr_t)coef, (const float *)(uintptr_t)resid,
                           (const float *)(uintptr_t)slack, (const float *)(uintptr_t)cmax,
                           (const float *)(uintptr_t)rmax, (const float *)(uintptr_t)smax,
                           (const double *)(uintptr_t)gram_max, y_error, e_max, n_groups, rank, m_rows, k_dir,
                           kernel_group(kernel)};
    /* work arrays: q (k_dir), work (2 (max_cand + 1)), ub and rg (G each); re, im (m_rows each) and
     * vs (2 n_virtual); cand (max_cand + 1); done (G) */
    double *q = malloc(sizeof(double) * (size_t)(k_dir + 2 * (max_cand + 1) + 2 * n_groups));
    float *re = malloc(sizeof(float) * (size_t)(2 * m_rows + 2 * n_virtual));
    int64_t *cand = malloc(sizeof(int64_t) * (size_t)(max_cand + 1));
    uint8_t *done = malloc((size_t)n_groups);
    if (q == NULL || re == NULL || cand == NULL || done == NULL) {
        free(q);
        free(re);
        free(cand);
        free(done);
        return PyErr_NoMemory();
    }
    double *work = q + k_dir, *ub = work + 2 * (max_cand + 1), *rg = ub + n_groups;
    Py_BEGIN_ALLOW_THREADS
    subspace_points((const float *)(uintptr_t)y, y_stride, &tb, (const float *)(uintptr_t)xn, n_points,
                    (const float *)(uintptr_t)v, (const float *)(uintptr_t)rows, n_virtual, n_az, n_el, max_cand,
                    row_norm_max, kernel_dot(kernel), (int64_t *)(uintptr_t)index, (float *)(uintptr_t)amplitude,
                    (uint8_t *)(uintptr_t)ambiguous, (uint8_t *)(uintptr_t)heavy, q, re, re + m_rows, ub, rg, done,
                    cand, re + 2 * m_rows, work);
    Py_END_ALLOW_THREADS
    free(q);
    free(re);
    free(cand);
    free(done);
    Py_RETURN_NONE;
}

/* ---------------------------------------------------------------- Python API ----------- */

PyDoc_STRVAR(certify_select_doc,
"certify_select(v, rows, n_virtual, ptr, kidx, n_points, n_az, n_el, index, amplitude, ambiguous,\n"
"               max_per_point)\n"
"--\n\n"
"Certified argmax over each point's candidate directions (see the module source). Addresses:\n"
"v complex64 (n_points, n_virtual); rows complex64 (n_az n_el, n_virtual); ptr int64\n"
"(n_points + 1,); kidx int64 candidate directions. Outputs index int64, amplitude float32,\n"
"ambiguous uint8, (n_points,) each. The GIL is released.");

static PyObject *py_certify_select(PyObject *self, PyObject *args)
{
    unsigned long long v, rows, ptr, kidx, index, amplitude, ambiguous;
    Py_ssize_t n_virtual, n_points, n_az, n_el, max_per_point;
    (void)self;
    if (!PyArg_ParseTuple(args, "KKnKKnnnKKKn", &v, &rows, &n_virtual, &ptr, &kidx, &n_points, &n_az, &n_el,
                          &index, &amplitude, &ambiguous, &max_per_point))
        return NULL;
    if (n_points < 0 || n_virtual < 1 || n_az < 1 || n_el < 1 || max_per_point < 0) {
        PyErr_Format(PyExc_ValueError, "need n_points >= 0, n_virtual, n_az, n_el >= 1 and max_per_point >= 0, "
                     "got %zd %zd %zd %zd %zd", n_points, n_virtual, n_az, n_el, max_per_point);
        return NULL;
    }
    if (n_points == 0)
        Py_RETURN_NONE;
    if (!v || !rows || !ptr || !kidx || !index || !amplitude || !ambiguous) {
        PyErr_SetString(PyExc_ValueError, "addresses must be non-null");
        return NULL;
    }
    double *work = malloc(sizeof(double) * (size_t)(2 * (max_per_point + 1)));
    if (work == NULL)
        return PyErr_NoMemory();
    Py_BEGIN_ALLOW_THREADS
    certify_points((const float *)(uintptr_t)v, (const float *)(uintptr_t)rows, n_virtual,
                   (const int64_t *)(uintptr_t)ptr, (const int64_t *)(uintptr_t)kidx, n_points, n_az, n_el,
                   (int64_t *)(uintptr_t)index, (float *)(uintptr_t)amplitude, (uint8_t *)(uintptr_t)ambiguous,
                   work);
    Py_END_ALLOW_THREADS
    free(work);
    Py_RETURN_NONE;
}



PyDoc_STRVAR(screen_select_doc,
"screen_select(y, y_stride, v, rows, beta, n_rows, n_az, n_el, n_virtual, alpha, max_cand,\n"
"              index, amplitude, heavy, kernel='auto')\n"
"--\n\n"
"Selection step of the screened beamformer for n_rows snapshots (see the module source).\n"
"Addresses: y bfloat16 (n_rows rows of stride y_stride >= 2 n_az n_el elements, [Re | Im],\n"
"elevation-major columns); v complex64 (n_rows, n_virtual); rows complex64\n"
"(n_az n_el, n_virtual), row k = az n_el + el; beta float32 (n_rows,). Outputs: index int64,\n"
"amplitude float32, heavy uint8, (n_rows,) each; heavy rows get index -1. The GIL is released.\n"
"kernel: 'auto', 'scalar' or 'avx' (the dot products). Returns (heavy rows, kernel that ran).");

static PyObject *py_screen_select(PyObject *self, PyObject *args)
{
    unsigned long long y, v, rows, beta, index, amplitude, heavy;
    Py_ssize_t y_stride, n_rows, n_az, n_el, n_virtual, max_cand;
    double alpha;
    const char *name = "auto";
    (void)self;
    if (!PyArg_ParseTuple(args, "KnKKKnnnndnKKK|s", &y, &y_stride, &v, &rows, &beta, &n_rows, &n_az,
                          &n_el, &n_virtual, &alpha, &max_cand, &index, &amplitude, &heavy, &name))
        return NULL;
    const int kernel = kernel_by_name(name);
    if (kernel < 0)
        return NULL;
    if (n_rows < 0 || n_az < 1 || n_el < 1 || n_virtual < 1 || max_cand < 1 || y_stride < 2 * n_az * n_el) {
        PyErr_Format(PyExc_ValueError, "need n_rows >= 0, n_az, n_el, n_virtual, max_cand >= 1 and "
                     "y_stride >= 2 n_az n_el, got n_rows=%zd n_az=%zd n_el=%zd n_virtual=%zd "
                     "max_cand=%zd y_stride=%zd", n_rows, n_az, n_el, n_virtual, max_cand, y_stride);
        return NULL;
    }
    if (!(alpha >= 0.0 && alpha < 1.0)) {
        PyErr_Format(PyExc_ValueError, "need 0 <= alpha < 1, got %g", alpha);
        return NULL;
    }
    if (n_rows == 0)
        return Py_BuildValue("(ns)", (Py_ssize_t)0, kernel_names[kernel]);
    if (!y || !v || !rows || !beta || !index || !amplitude || !heavy) {
        PyErr_SetString(PyExc_ValueError, "addresses must be non-null");
        return NULL;
    }
    scratch_t w;
    w.q_az = malloc(sizeof(float) * (size_t)(2 * n_az + 2 * n_virtual));
    if (w.q_az == NULL)
        return PyErr_NoMemory();
    w.check = w.q_az + n_az;
    w.vs = w.check + n_az;
    Py_BEGIN_ALLOW_THREADS
    select_rows((const uint16_t *)(uintptr_t)y, y_stride, (const float *)(uintptr_t)v,
                (const float *)(uintptr_t)rows, (const float *)(uintptr_t)beta, n_rows, n_az, n_el,
                n_virtual, alpha, max_cand, (int64_t *)(uintptr_t)index,
                (float *)(uintptr_t)amplitude, (uint8_t *)(uintptr_t)heavy, kernel_dot(kernel), &w);
    Py_END_ALLOW_THREADS
    free(w.q_az);
    Py_ssize_t n_heavy = 0;
    const uint8_t *h = (const uint8_t *)(uintptr_t)heavy;
    for (Py_ssize_t j = 0; j < n_rows; ++j)
        n_heavy += h[j];
    return Py_BuildValue("(ns)", n_heavy, kernel_names[kernel]);
}

PyDoc_STRVAR(kernels_doc,
"kernels()\n"
"--\n\n"
"Names of the dot-product kernels this build can run on this CPU, fastest first.");

static PyObject *py_kernels(PyObject *self, PyObject *args)
{
    (void)self;
    (void)args;
    if (kernel_on_cpu(KERNEL_AVX))
        return Py_BuildValue("(ss)", kernel_names[KERNEL_AVX], kernel_names[KERNEL_SCALAR]);
    return Py_BuildValue("(s)", kernel_names[KERNEL_SCALAR]);
}

static PyMethodDef screen_methods[] = {
    {"screen_select", py_screen_select, METH_VARARGS, screen_select_doc},
    {"kernels", py_kernels, METH_NOARGS, kernels_doc},
    {"certify_select", py_certify_select, METH_VARARGS, certify_select_doc},
    {"subspace_select", py_subspace_select, METH_VARARGS, subspace_select_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef screen_module = {
    PyModuleDef_HEAD_INIT, "_screen",
    "Native CPU kernel for radarpc.dsp.accel.native: the selection step of the screened beamformer.",
    -1, screen_methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__screen(void)
{
#if SCREEN_X86_SIMD
    __builtin_cpu_init();
#endif
    return PyModule_Create(&screen_module);
}
