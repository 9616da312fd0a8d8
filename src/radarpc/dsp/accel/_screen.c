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
 * compiler's own vectorisation of the scalar one was 5x slower), chosen at run time. The entry point takes raw addresses and a row
 * range and releases the GIL, so Python threads can run disjoint row ranges in parallel.
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
static double dot_abs_f64(const float *b, const float *v, Py_ssize_t n, double *bound)
{
    double re0 = 0.0, re1 = 0.0, im0 = 0.0, im1 = 0.0, s1 = 0.0;
    for (Py_ssize_t i = 0; i < n; ++i) {
        const double br = b[2 * i], bi = b[2 * i + 1], vr = v[2 * i], vi = v[2 * i + 1];
        re0 += br * vr;
        re1 += bi * vi;
        im0 += br * vi;
        im1 += bi * vr;
        s1 += (fabs(br) + fabs(bi)) * (fabs(vr) + fabs(vi));
    }
    const double re = re0 - re1, im = im0 + im1;
    const double f = sqrt(re * re + im * im);
    const double m = (double)(2 * n + 2) * 0x1p-53;
    *bound = 1.5 * (m / (1.0 - m)) * s1 * (1.0 + 0x1p-40) + 0x1p-50 * f;
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
 * With |s_k - z^_k| <= e_k = slack_k xn_j and a_k = |z^_k| (q_k = a_k^2 in double: products of
 * float32 values are exact), L = a_b - e_b for b = argmax q is a lower bound of max_k |s_k|, and
 * k is a candidate when a_k + e_k >= L, tested as q_k >= (L - slack_k xn)^2 (or L - slack_k xn
 * <= 0); L is lowered by 2^-40 (a_b + max slack xn), far more than the double rounding of the
 * test. The candidates are decided as in certify_points. More than max_cand candidates or a
 * non-finite screen or norm -> heavy (index -1; the caller runs the exact beamformer). */
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

/* Group pruning: |z^_k| <= ||c_k|| ||y_g|| + |z^_k - c_k . y_g| <= cmax_g ||y_g|| + slack_k xn (the
 * second product's rounding is part of the slack), so no direction of group g can be a candidate
 * (a_k + e_k >= L) when ub_g = cmax_g ||y_g|| + 2 smax_g xn < L. The group with the largest ub
 * is screened first; every other group only if its ub reaches the lower bound L of the groups
 * screened so far (L is their largest, so a skipped group stays below the final L). ||y_g|| is summed
 * in double from float32 values (relative error < 2r 2^-53, covered by the 2^-20 inflation). */
static Py_ssize_t subspace_points_one(const float *y, const float *coef, const float *slack, const float *cmax,
                                      const float *smax, double slack_max, double x, Py_ssize_t n_groups, Py_ssize_t rank,
                                      Py_ssize_t m_rows, Py_ssize_t k_dir, Py_ssize_t max_cand, double *q,
                                      float *re, float *im, double *ub, uint8_t *done, int64_t *cand, int *finite)
{
    double qb = -1.0, bad = 0.0, low = -INFINITY;
    Py_ssize_t kb = 0, g0 = 0;
    for (Py_ssize_t g = 0; g < n_groups; ++g) {
        const float *yg = y + 2 * rank * g;
        double n2 = 0.0;
        for (Py_ssize_t u = 0; u < 2 * rank; ++u)
            n2 += (double)yg[u] * yg[u];
        ub[g] = ((double)cmax[g] * sqrt(n2) + 2.0 * (double)smax[g] * x) * (1.0 + 0x1p-20);
        bad += ub[g] * 0.0;
        done[g] = 0;
        if (ub[g] > ub[g0])
            g0 = g;
    }
    if (bad != 0.0 || !isfinite(x)) {
        *finite = 0;
        return 0;
    }
    for (Py_ssize_t step = -1; step < n_groups; ++step) {
        const Py_ssize_t g = step < 0 ? g0 : step;
        if (done[g] || ub[g] < low)
            continue;
        const Py_ssize_t k0 = g * m_rows, m = k0 + m_rows <= k_dir ? m_rows : k_dir - k0;
        subspace_group(y + 2 * rank * g, coef + 2 * rank * m_rows * g, rank, m_rows, m, re, im, q + k0);
        done[g] = 1;
        for (Py_ssize_t t = 0; t < m; ++t) {
            bad += q[k0 + t] * 0.0;
            if (q[k0 + t] > qb) {
                qb = q[k0 + t];
                kb = k0 + t;
            }
        }
        if (bad != 0.0) {
            *finite = 0;
            return 0;
        }
        /* L = a_b - e_b, lowered by 2^-40 (a_b + max slack xn) for the double rounding of the tests;
         * each such L bounds max |s| from below, so the largest so far is kept (a new best b with a
         * larger slack may give a smaller one) */
        const double ab = sqrt(qb);
        const double lb = ab * (1.0 - 0x1p-50) - (double)slack[kb] * x - 0x1p-40 * (ab + slack_max * x);
        if (lb > low)
            low = lb;
    }
    *finite = 1;
    Py_ssize_t n_cand = 0;
    for (Py_ssize_t g = 0; g < n_groups && n_cand <= max_cand; ++g) {
        if (!done[g])
            continue;
        const Py_ssize_t k0 = g * m_rows, k1 = k0 + m_rows <= k_dir ? k0 + m_rows : k_dir;
        for (Py_ssize_t k = k0; k < k1 && n_cand <= max_cand; ++k) {
            const double rhs = low - (double)slack[k] * x;
            if (rhs <= 0.0 || q[k] >= rhs * rhs)
                cand[n_cand++] = k;
        }
    }
    return n_cand;
}

/* Many candidates (flat, noise-like spectra): a float32 pass first. f_k = |B[k] . v| from the
 * float32 dot kernel; each of Re and Im is a sum of 2N float32 products in any order, so it is
 * within gamma_(2N+1) sum (|br| + |bi|)(|vr| + |vi|) <= gamma_(2N+1) 2 ||B[k]|| ||v|| of the exact
 * value, and |f_k - |s_k|| <= e = 2 sqrt(2) gamma_(2N+2) R ||v|| + 2^-22 f_k (R = max_k ||B[k]||;
 * the last term covers the modulus in double and its float32 rounding). Only candidates with
 * f_k + e_k >= f_b - e_b (b the largest f) can hold the maximum; they go to certify_points. */
#define REFINE_MIN 8

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
    double best = -1.0, best_e = 0.0;
    for (Py_ssize_t p = 0; p < n_cand; ++p) {
        const double f = dot(rows + 2 * n_virtual * cand[p], vj, vs, n_virtual);
        work[p] = f;
        if (f > best) {
            best = f;
            best_e = base + 0x1p-22 * f;
        }
    }
    if (!(best >= 0.0) || !isfinite(best) || !isfinite(base))   /* NaN or overflow: keep them all */
        return n_cand;
    const double low = best - best_e;
    Py_ssize_t kept = 0;
    for (Py_ssize_t p = 0; p < n_cand; ++p)
        if (!(work[p] + base + 0x1p-22 * work[p] < low))      /* a NaN value is kept */
            cand[kept++] = cand[p];                           /* ascending order is kept */
    return kept;
}

static void subspace_points(const float *y, Py_ssize_t y_stride, const float *coef, const float *slack,
                            const float *cmax, const float *smax, double slack_max, const float *xn,
                            Py_ssize_t n_groups, Py_ssize_t rank, Py_ssize_t m_rows, Py_ssize_t k_dir,
                            Py_ssize_t n_points, const float *v, const float *rows, Py_ssize_t n_virtual,
                            Py_ssize_t n_az, Py_ssize_t n_el, Py_ssize_t max_cand, double row_norm_max,
                            dot_abs_fn dot, int64_t *index, float *amplitude, uint8_t *ambiguous, uint8_t *heavy,
                            double *q, float *re, float *im, double *ub, uint8_t *done, int64_t *cand,
                            float *vs, double *work)
{
    for (Py_ssize_t j = 0; j < n_points; ++j) {
        int finite;
        Py_ssize_t n_cand = subspace_points_one(y + y_stride * j, coef, slack, cmax, smax, slack_max, (double)xn[j],
                                                n_groups, rank, m_rows, k_dir, max_cand, q, re, im, ub, done, cand,
                                                &finite);
        if (!finite || n_cand == 0 || n_cand > max_cand) {
            heavy[j] = 1;
            index[j] = -1;
            amplitude[j] = 0.0f;
            ambiguous[j] = 0;
            continue;
        }
        heavy[j] = 0;
        const float *vj = v + 2 * n_virtual * j;
        if (n_cand > REFINE_MIN)
            n_cand = refine_f32(vj, rows, n_virtual, cand, n_cand, row_norm_max, (double)xn[j], dot, vs, work);
        const int64_t ptr[2] = {0, (int64_t)n_cand};
        certify_points(vj, rows, n_virtual, ptr, cand, 1, n_az, n_el, index + j, amplitude + j, ambiguous + j,
                       work);
    }
}

PyDoc_STRVAR(subspace_select_doc,
"subspace_select(y, y_stride, coef, slack, cmax, smax, slack_max, xn, n_groups, rank, m_rows, k_dir,\n"
"                n_points, v, rows, n_virtual, n_az, n_el, max_cand, row_norm_max, index, amplitude,\n"
"                ambiguous, heavy, kernel='auto')\n"
"--\n\n"
"Screen, selection and certified decision of the subspace beamformer for n_points points (see\n"
"the module source). Addresses: y float32 rows of y_stride elements (G 2 rank used); coef\n"
"float32 (G, 2, rank, m_rows); slack float32 (k_dir,); cmax, smax float32 (G,) (largest\n"
"coefficient norm and slack of each group); xn float32 (n_points,) (snapshot norms, rounded up);\n"
"v complex64 (n_points, n_virtual); rows complex64 (k_dir, n_virtual); row_norm_max >= max_k\n"
"||rows[k]||; kernel 'auto', 'scalar' or 'avx' (the float32 dot of points with many candidates).\n"
"Outputs index int64, amplitude float32, ambiguous uint8, heavy uint8. The GIL is released.");

static PyObject *py_subspace_select(PyObject *self, PyObject *args)
{
    unsigned long long y, coef, slack, cmax, smax, xn, v, rows, index, amplitude, ambiguous, heavy;
    Py_ssize_t y_stride, n_groups, rank, m_rows, k_dir, n_points, n_virtual, n_az, n_el, max_cand;
    double slack_max, row_norm_max;
    const char *name = "auto";
    (void)self;
    if (!PyArg_ParseTuple(args, "KnKKKKdKnnnnnKKnnnndKKKK|s", &y, &y_stride, &coef, &slack, &cmax, &smax,
                          &slack_max, &xn, &n_groups, &rank, &m_rows, &k_dir, &n_points, &v, &rows, &n_virtual, &n_az,
                          &n_el, &max_cand, &row_norm_max, &index, &amplitude, &ambiguous, &heavy, &name))
        return NULL;
    const int kernel = kernel_by_name(name);
    if (kernel < 0)
        return NULL;
    if (n_points < 0 || n_groups < 1 || rank < 1 || m_rows < 1 || k_dir < 1 || k_dir > n_groups * m_rows
        || n_virtual < 1 || n_az * n_el != k_dir || max_cand < 1 || y_stride < 2 * rank * n_groups) {
        PyErr_SetString(PyExc_ValueError, "subspace_select: inconsistent sizes");
        return NULL;
    }
    if (n_points == 0)
        Py_RETURN_NONE;
    if (max_cand > k_dir)
        max_cand = k_dir;
    double *q = malloc(sizeof(double) * (size_t)(k_dir + 2 * (max_cand + 1) + n_groups));
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
    Py_BEGIN_ALLOW_THREADS
    subspace_points((const float *)(uintptr_t)y, y_stride, (const float *)(uintptr_t)coef,
                    (const float *)(uintptr_t)slack, (const float *)(uintptr_t)cmax, (const float *)(uintptr_t)smax,
                    slack_max, (const float *)(uintptr_t)xn, n_groups, rank, m_rows, k_dir, n_points,
                    (const float *)(uintptr_t)v, (const float *)(uintptr_t)rows, n_virtual, n_az, n_el, max_cand,
                    row_norm_max, kernel_dot(kernel), (int64_t *)(uintptr_t)index, (float *)(uintptr_t)amplitude,
                    (uint8_t *)(uintptr_t)ambiguous, (uint8_t *)(uintptr_t)heavy, q, re, re + m_rows,
                    q + k_dir + 2 * (max_cand + 1), done, cand, re + 2 * m_rows, q + k_dir);
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
