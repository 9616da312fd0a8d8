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

/* ---------------------------------------------------------------- Python API ----------- */

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
    int kernel = -1;
    for (int k = 0; k < (int)(sizeof(kernel_names) / sizeof(kernel_names[0])); ++k)
        if (strcmp(name, kernel_names[k]) == 0)
            kernel = k;
    if (kernel == KERNEL_AUTO)
        kernel = kernel_on_cpu(KERNEL_AVX) ? KERNEL_AVX : KERNEL_SCALAR;
    if (kernel < 0 || !kernel_on_cpu(kernel)) {
        PyErr_Format(PyExc_ValueError, "kernel '%s' is not one of 'auto', 'scalar', 'avx' or cannot run on "
                     "this build/CPU", name);
        return NULL;
    }
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
