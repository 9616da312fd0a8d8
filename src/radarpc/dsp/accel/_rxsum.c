/* radarpc.dsp.accel._rxsum: native CPU kernel for the RD magnitude sum A = sum_rx |R|.
 *
 * Input: n_cells contiguous cells of n_rx complex64 values (re, im interleaved), i.e. the
 * flattened (..., Nd, Nrx) cube; output: n_cells float32, A[c] = sum_r sqrt(re^2 + im^2).
 *
 * Every kernel computes |z| = sqrtf(re*re + im*im) with IEEE sqrt (no rsqrt approximation, no
 * fused multiply-add: setup.py passes -ffp-contract=off), exactly as torch's blocked fallback
 * does element by element; only the order of the receiver sum differs (a tree instead of a
 * left-to-right sum), which changes A by a few float32 ulps at most.
 *
 * Kernels (chosen at run time, see kernel_supported):
 *   scalar  any n_rx, any CPU (plain C)
 *   avx     n_rx % 8 == 0, x86 with AVX: 8 cells per step; re/im deinterleaved in-lane (the
 *           receiver order inside a register does not matter for the sum), 8-wide sqrt, and a
 *           shuffle tree that turns the 8 per-cell vectors into the 8 sums
 * The SIMD kernel is compiled only with GCC/Clang on x86 (function target attribute); MSVC,
 * ARM and other compilers get the scalar kernel. A 16-cell AVX-512 version of the same scheme
 * (tried before the software prefetch was added) measured 5-15 % slower than the AVX one on a
 * Sapphire Rapids host: sqrt throughput per float is the same for 256- and 512-bit vectors
 * there, and with 2 threads the pass is bound by memory reads (this kernel runs within ~10 %
 * of a plain AVX read-and-add loop over the cube).
 *
 * The entry point releases the GIL itself and takes raw addresses,
 * so that Python threads can run disjoint cell ranges in parallel.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <string.h>

/* Define RXSUM_NO_SIMD to build only the portable scalar kernel (as on MSVC / ARM). */
#if !defined(RXSUM_NO_SIMD) && (defined(__GNUC__) || defined(__clang__)) && (defined(__x86_64__) || defined(__i386__))
#define RXSUM_X86_SIMD 1
#include <immintrin.h>
#define RXSUM_TARGET(t) __attribute__((target(t)))
#define RXSUM_PRAGMA(x) _Pragma(#x)
#define RXSUM_UNROLL RXSUM_PRAGMA(GCC unroll 16)
#else
#define RXSUM_X86_SIMD 0
#endif

enum { KERNEL_AUTO = 0, KERNEL_SCALAR = 1, KERNEL_AVX = 2 };

static const char *const kernel_names[] = {"auto", "scalar", "avx"};

/* ---------------------------------------------------------------- scalar -------------- */

static void rxsum_scalar(const float *x, float *out, Py_ssize_t n_cells, Py_ssize_t n_rx)
{
    for (Py_ssize_t c = 0; c < n_cells; ++c) {
        const float *p = x + 2 * n_rx * c;
        float s = 0.0f;
        for (Py_ssize_t r = 0; r < n_rx; ++r) {
            const float re = p[2 * r], im = p[2 * r + 1];
            s += sqrtf(re * re + im * im);
        }
        out[c] = s;
    }
}

#if RXSUM_X86_SIMD
/* ---------------------------------------------------------------- AVX (8 lanes) -------- */

/* |z| of 8 consecutive complex values at p (any receiver order: the caller sums them). */
RXSUM_TARGET("avx") static inline __attribute__((always_inline)) __m256 mag8(const float *p)
{
    const __m256 a = _mm256_loadu_ps(p), b = _mm256_loadu_ps(p + 8);
    const __m256 re = _mm256_shuffle_ps(a, b, _MM_SHUFFLE(2, 0, 2, 0));
    const __m256 im = _mm256_shuffle_ps(a, b, _MM_SHUFFLE(3, 1, 3, 1));
    return _mm256_sqrt_ps(_mm256_add_ps(_mm256_mul_ps(re, re), _mm256_mul_ps(im, im)));
}

/* Eight lane-partials of one cell: sum over its n_rx / 8 groups of 8 receivers. */
RXSUM_TARGET("avx") static inline __attribute__((always_inline)) __m256 cell8(const float *p, Py_ssize_t groups)
{
    __m256 acc = mag8(p);
    for (Py_ssize_t g = 1; g < groups; ++g)
        acc = _mm256_add_ps(acc, mag8(p + 16 * g));
    return acc;
}

/* A[c .. c+8) for the 8 cells at base. Always inlined so that the caller's constant `groups`
 * (n_rx = 8 or 16) unrolls fully and m[] stays in registers. */
RXSUM_TARGET("avx") static inline __attribute__((always_inline))
void block8(const float *base, Py_ssize_t groups, float *out)
{
    /* The shuffle tree below leaves slot s of m[] in lane 4 (s % 2) + s / 2; loading cell
     * order[s] into slot s puts cell l in lane l (cheaper, measured, than loading in order and
     * permuting the result, which would also need AVX2). */
    static const int order[8] = {0, 4, 1, 5, 2, 6, 3, 7};
    const Py_ssize_t stride = 16 * groups;
    __m256 m[8], t[4], u[2];
    RXSUM_UNROLL
    for (int s = 0; s < 8; ++s)                                      /* 8 partials per cell */
        m[s] = cell8(base + stride * order[s], groups);
    RXSUM_UNROLL
    for (int k = 0; k < 4; ++k)                                      /* 4 partials, 2 cells */
        t[k] = _mm256_add_ps(_mm256_permute2f128_ps(m[2 * k], m[2 * k + 1], 0x20),
                             _mm256_permute2f128_ps(m[2 * k], m[2 * k + 1], 0x31));
    RXSUM_UNROLL
    for (int k = 0; k < 2; ++k)                                      /* 2 partials, 4 cells */
        u[k] = _mm256_add_ps(_mm256_shuffle_ps(t[2 * k], t[2 * k + 1], _MM_SHUFFLE(2, 0, 2, 0)),
                             _mm256_shuffle_ps(t[2 * k], t[2 * k + 1], _MM_SHUFFLE(3, 1, 3, 1)));
    _mm256_storeu_ps(out, _mm256_add_ps(_mm256_shuffle_ps(u[0], u[1], _MM_SHUFFLE(2, 0, 2, 0)),
                                        _mm256_shuffle_ps(u[0], u[1], _MM_SHUFFLE(3, 1, 3, 1))));
}

/* Software prefetch into L2 this many bytes ahead of the block being summed. Measured on the
 * 16-Rx RADIal cube: ~15 % faster than the hardware prefetchers alone with 1 and 2 threads, for
 * any distance from 4 to 64 KB (prefetching into L1 or non-temporally was slower). */
#define RXSUM_PREFETCH_BYTES 16384

/* Sum the whole 8-cell blocks of x; returns the number of cells done. Always inlined so that
 * the callers' constant `groups` specialises the loops. */
RXSUM_TARGET("avx") static inline __attribute__((always_inline))
Py_ssize_t blocks8(const float *x, float *out, Py_ssize_t n_cells, Py_ssize_t groups)
{
    const Py_ssize_t cell = 16 * groups;                             /* floats per cell */
    const Py_ssize_t ahead = RXSUM_PREFETCH_BYTES / (4 * cell);      /* cells */
    Py_ssize_t c = 0;
    for (; c + ahead + 8 <= n_cells; c += 8) {                       /* prefetch target inside x */
        const float *p = x + cell * (c + ahead);
        RXSUM_UNROLL
        for (Py_ssize_t l = 0; l < cell / 2; ++l)                    /* the block's 64-byte lines */
            _mm_prefetch((const char *)(p + 16 * l), _MM_HINT_T1);
        block8(x + cell * c, groups, out + c);
    }
    for (; c + 8 <= n_cells; c += 8)
        block8(x + cell * c, groups, out + c);
    return c;
}

RXSUM_TARGET("avx")
static void rxsum_avx(const float *x, float *out, Py_ssize_t n_cells, Py_ssize_t n_rx)
{
    const Py_ssize_t groups = n_rx / 8;
    Py_ssize_t c;
    if (groups == 2)                                                 /* RADIal: 16 Rx */
        c = blocks8(x, out, n_cells, 2);
    else if (groups == 1)
        c = blocks8(x, out, n_cells, 1);
    else
        c = blocks8(x, out, n_cells, groups);
    rxsum_scalar(x + 2 * n_rx * c, out + c, n_cells - c, n_rx);
}
#endif /* RXSUM_X86_SIMD */

/* ---------------------------------------------------------------- dispatch ------------- */

/* Whether this build and this CPU can run `kernel` (ignoring n_rx). */
static int kernel_on_cpu(int kernel)
{
    switch (kernel) {
    case KERNEL_SCALAR:
        return 1;
#if RXSUM_X86_SIMD
    case KERNEL_AVX:
        return __builtin_cpu_supports("avx");
#endif
    default:
        return 0;
    }
}

static int kernel_supported(int kernel, Py_ssize_t n_rx)
{
    if (!kernel_on_cpu(kernel))
        return 0;
    if (kernel == KERNEL_AVX)
        return n_rx % 8 == 0;
    return 1;
}

static int best_kernel(Py_ssize_t n_rx)
{
    if (kernel_supported(KERNEL_AVX, n_rx))
        return KERNEL_AVX;
    return KERNEL_SCALAR;
}

static void run_kernel(int kernel, const float *x, float *out, Py_ssize_t n_cells, Py_ssize_t n_rx)
{
    switch (kernel) {
#if RXSUM_X86_SIMD
    case KERNEL_AVX:
        rxsum_avx(x, out, n_cells, n_rx);
        return;
#endif
    default:
        rxsum_scalar(x, out, n_cells, n_rx);
    }
}

/* ---------------------------------------------------------------- Python API ----------- */

static int parse_kernel(const char *name)
{
    for (int k = 0; k < (int)(sizeof(kernel_names) / sizeof(kernel_names[0])); ++k)
        if (strcmp(name, kernel_names[k]) == 0)
            return k;
    return -1;
}

PyDoc_STRVAR(rx_magnitude_sum_doc,
"rx_magnitude_sum(src, dst, n_cells, n_rx, kernel='auto')\n"
"--\n\n"
"out[c] = sum_r |x[c, r]| for n_cells cells of n_rx complex64 values at address src, written\n"
"as n_cells float32 at address dst. Both buffers must be valid, contiguous and not overlap;\n"
"the GIL is released while computing. kernel: 'auto', 'scalar' or 'avx'.\n"
"Returns the name of the kernel that ran.");

static PyObject *py_rx_magnitude_sum(PyObject *self, PyObject *args)
{
    unsigned long long src, dst;
    Py_ssize_t n_cells, n_rx;
    const char *name = "auto";
    (void)self;
    if (!PyArg_ParseTuple(args, "KKnn|s", &src, &dst, &n_cells, &n_rx, &name))
        return NULL;
    if (n_cells < 0 || n_rx < 1) {
        PyErr_Format(PyExc_ValueError, "need n_cells >= 0 and n_rx >= 1, got n_cells=%zd, n_rx=%zd",
                     n_cells, n_rx);
        return NULL;
    }
    int kernel = parse_kernel(name);
    if (kernel < 0) {
        PyErr_Format(PyExc_ValueError, "kernel must be 'auto', 'scalar' or 'avx', got '%s'", name);
        return NULL;
    }
    if (kernel == KERNEL_AUTO) {
        kernel = best_kernel(n_rx);
    } else if (!kernel_supported(kernel, n_rx)) {
        PyErr_Format(PyExc_ValueError, "kernel '%s' is not available for n_rx=%zd on this build/CPU "
                     "(avx needs n_rx %% 8 == 0 and an AVX CPU)", name, n_rx);
        return NULL;
    }
    if (n_cells > 0 && (src == 0 || dst == 0)) {
        PyErr_SetString(PyExc_ValueError, "src and dst must be non-null addresses");
        return NULL;
    }
    const float *x = (const float *)(uintptr_t)src;
    float *out = (float *)(uintptr_t)dst;
    Py_BEGIN_ALLOW_THREADS
    run_kernel(kernel, x, out, n_cells, n_rx);
    Py_END_ALLOW_THREADS
    return PyUnicode_FromString(kernel_names[kernel]);
}

PyDoc_STRVAR(kernels_doc,
"kernels(n_rx=16)\n"
"--\n\n"
"Names of the kernels this build can run on this CPU for n_rx receivers, fastest first.");

static PyObject *py_kernels(PyObject *self, PyObject *args)
{
    Py_ssize_t n_rx = 16;
    (void)self;
    if (!PyArg_ParseTuple(args, "|n", &n_rx))
        return NULL;
    PyObject *out = PyList_New(0);
    if (out == NULL)
        return NULL;
    static const int order[] = {KERNEL_AVX, KERNEL_SCALAR};
    for (size_t i = 0; i < sizeof(order) / sizeof(order[0]); ++i) {
        if (n_rx >= 1 && kernel_supported(order[i], n_rx)) {
            PyObject *s = PyUnicode_FromString(kernel_names[order[i]]);
            if (s == NULL || PyList_Append(out, s) < 0) {
                Py_XDECREF(s);
                Py_DECREF(out);
                return NULL;
            }
            Py_DECREF(s);
        }
    }
    PyObject *tuple = PyList_AsTuple(out);
    Py_DECREF(out);
    return tuple;
}

static PyMethodDef rxsum_methods[] = {
    {"rx_magnitude_sum", py_rx_magnitude_sum, METH_VARARGS, rx_magnitude_sum_doc},
    {"kernels", py_kernels, METH_VARARGS, kernels_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef rxsum_module = {
    PyModuleDef_HEAD_INIT, "_rxsum",
    "Native CPU kernel for radarpc.dsp.accel.native: A = sum_rx |R| over complex64 cells.",
    -1, rxsum_methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__rxsum(void)
{
#if RXSUM_X86_SIMD
    __builtin_cpu_init();
#endif
    return PyModule_Create(&rxsum_module);
}
