/*
 * Hot loops of perscli, compiled once at install time.
 *
 * Why C and not numpy or numba: apply-persistence streams ten or more
 * 4088x4088 frames.  numpy needs five passes over each frame (convert,
 * compare, clip, scale, add) and numba costs ~0.5 s of start-up per process,
 * which is more than the whole computation; a single pass in C over a block
 * of the frame's on-disk (big-endian) bytes does the byte swap, the fluence
 * model, the accumulation and the FITS DATASUM in one go.
 *
 * The functions take Python buffers (numpy arrays, memmaps, bytes) and
 * release the GIL so that callers may split a frame across threads.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <float.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

enum { K_F4 = 0, K_F8 = 1 };

/* Decode a struct-module format string ('>f', '<d', 'f', '=d', ...) into a
 * kind and whether the bytes need swapping on this machine. */
static int
parse_format(const char *fmt, int *kind, int *swap)
{
    const int little = (*(const uint16_t *)"\x01\x00") == 1;
    int big = !little;
    if (fmt == NULL) fmt = "B";
    if (*fmt == '>' || *fmt == '!') { big = 1; fmt++; }
    else if (*fmt == '<') { big = 0; fmt++; }
    else if (*fmt == '=' || *fmt == '@') { fmt++; }
    if (strcmp(fmt, "f") == 0) *kind = K_F4;
    else if (strcmp(fmt, "d") == 0) *kind = K_F8;
    else return -1;
    *swap = (big == little);
    return 0;
}

static inline double
load_f4(const unsigned char *base, Py_ssize_t i, int swap, uint64_t *sum)
{
    uint32_t u;
    float f;
    memcpy(&u, base + 4 * i, 4);
    if (swap) u = __builtin_bswap32(u);
    /* DATASUM adds the big-endian words; on a big-endian file that is u */
    *sum += u;
    memcpy(&f, &u, 4);
    return (double)f;
}

static inline double
load_f8(const unsigned char *base, Py_ssize_t i, int swap, uint64_t *sum)
{
    uint64_t u;
    double d;
    memcpy(&u, base + 8 * i, 8);
    if (swap) u = __builtin_bswap64(u);
    *sum += (u >> 32) + (u & 0xFFFFFFFFu);
    memcpy(&d, &u, 8);
    return d;
}

typedef struct {
    int linear_only;      /* 1: F(x) = x (GalSim's linear model, no clipping) */
    double A, x0, dx, alpha, half_well, slope;
} fluence_model;

/* F(x): the persistence current at t = 1000 s (e-/s), the paper's Fermi law
 * above half_well and a straight line through the origin below it. */
static inline double
fluence_law(const fluence_model *m, double x)
{
    if (m->linear_only) return x;
    if (x > m->half_well)
        return m->A * pow(x / m->x0, m->alpha) / (exp(-(x - m->x0) / m->dx) + 1.0);
    if (x > 0.0) return m->slope * x;
    return 0.0;
}

/* One loop per storage type, byte order and model kind, so that none of
 * them is tested per pixel; the DATASUM of the bytes is gathered on the way
 * (it is only meaningful when x holds the bytes as stored in big-endian
 * FITS).  The common case, one plane summed, keeps the Fermi law off the
 * hot path: below half_well the charge is one multiply-add. */
#define FOLD(sum) ((sum) = ((sum) & 0xFFFFFFFFu) + ((sum) >> 32))
#define ACCUMULATE_LOOP(LOAD, SWAP)                                            \
    if (nk == 1 && !combine_max && !m.linear_only) {                           \
        const double t0 = T[0], lin = T[0] * m.slope * scale;                  \
        for (Py_ssize_t i = start; i < stop; i++) {                            \
            double v = LOAD(xs, i, SWAP, &sum);                                \
            if ((i & 0x3FFFFF) == 0x3FFFFF) FOLD(sum);                         \
            double x = v * scale;                                              \
            if (x > m.half_well) {                                             \
                if (!isfinite(x)) { nonfinite++; continue; }                   \
                acc[i] += t0 * fluence_law(&m, x);                             \
            } else if (x > 0.0) {                                              \
                acc[i] += lin * v;                                             \
            } else if (!isfinite(x)) {                                         \
                nonfinite++;                                                   \
            }                                                                  \
        }                                                                      \
    } else {                                                                   \
        for (Py_ssize_t i = start; i < stop; i++) {                            \
            double v = LOAD(xs, i, SWAP, &sum);                                \
            if ((i & 0x3FFFFF) == 0x3FFFFF) FOLD(sum);                         \
            if (!isfinite(v)) { nonfinite++; continue; }                       \
            double f = fluence_law(&m, v * scale);                             \
            for (Py_ssize_t k = 0; k < nk; k++) {                              \
                double q = T[k] * f;                                           \
                double *a = acc + k * npix + i;                                \
                if (combine_max) { if (q > *a) *a = q; }                       \
                else *a += q;                                                  \
            }                                                                  \
        }                                                                      \
    }

/* The common case in a form the compiler vectorises: float32 rows, one
 * plane, sums.  A chunk of pixels is converted, checksummed and given the
 * linear law without a branch; a pixel outside [-half_well, half_well] (the
 * Fermi law's domain, or NaN/inf) adds nothing there and sends the chunk
 * through a second, scalar pass for those pixels alone.  The result is bit
 * for bit that of the scalar loop: skipped pixels add +0.0. */
#define CHUNK_PIX 2048

/* Two vectorisable passes over a chunk: the checksum and byte swap into
 * native floats, then the linear law.  Compiled for AVX2, SSE4.2 and the
 * baseline, chosen at load time (GCC's target_clones); the baseline has no
 * vector blend and stays scalar, with the same results. */
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__)
#define PERSCLI_CLONES __attribute__((target_clones("avx2", "sse4.2", "default")))
#else
#define PERSCLI_CLONES
#endif

PERSCLI_CLONES static uint64_t
swap_and_sum_f4(const uint32_t *restrict words, float *restrict out, Py_ssize_t n, int swap)
{
    uint64_t s = 0;
    if (swap) {
        for (Py_ssize_t i = 0; i < n; i++) {
            const uint32_t u = __builtin_bswap32(words[i]);
            s += u;
            memcpy(out + i, &u, 4);
        }
    } else {
        for (Py_ssize_t i = 0; i < n; i++) {
            const uint32_t u = words[i];
            s += u;
            memcpy(out + i, &u, 4);
        }
    }
    return s;
}

PERSCLI_CLONES static long
linear_law_f4(const float *restrict v, double *restrict acc, Py_ssize_t n, double scale, double hw, double lin)
{
    long outside = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        const double x = (double)v[i] * scale, a = lin * (double)v[i];
        const long in = fabs(x) <= hw;
        outside |= in ^ 1;
        acc[i] += (fabs(x) <= hw && x > 0.0) ? a : 0.0;
    }
    return outside;
}

/* The common case: float32 rows, one plane, sums.  Each chunk is checksummed
 * and given the linear law without a branch; a pixel outside [-half_well,
 * half_well] (the Fermi law's domain, or NaN/inf) adds +0.0 there and sends
 * the chunk through a scalar pass for those pixels alone, so the result is
 * bit for bit that of the scalar loop. */
static void
accumulate_f4_linear_first(const unsigned char *xs, double *acc, Py_ssize_t start, Py_ssize_t stop,
                           int swap, double scale, double t0, const fluence_model *m,
                           uint64_t *sum_out, Py_ssize_t *nonfinite_out)
{
    const double hw = m->half_well, lin = t0 * m->slope * scale;
    uint64_t sum = *sum_out;
    Py_ssize_t nonfinite = 0;
    uint32_t words[CHUNK_PIX];
    float vals[CHUNK_PIX];
    for (Py_ssize_t c = start; c < stop; c += CHUNK_PIX) {
        const Py_ssize_t n = (stop - c < CHUNK_PIX) ? stop - c : CHUNK_PIX;
        memcpy(words, xs + 4 * c, 4 * n);   /* the rows need not be 4-byte aligned */
        sum += swap_and_sum_f4(words, vals, n, swap);
        FOLD(sum);
        if (linear_law_f4(vals, acc + c, n, scale, hw, lin)) {
            for (Py_ssize_t i = 0; i < n; i++) {
                const double x = (double)vals[i] * scale;
                if (fabs(x) <= hw) continue;
                if (!isfinite(x)) nonfinite++;
                else if (x > hw) acc[c + i] += t0 * fluence_law(m, x);
            }
        }
    }
    *sum_out = sum;
    *nonfinite_out += nonfinite;
}

static PyObject *
accumulate(PyObject *self, PyObject *args)
{
    Py_buffer xb, ab;
    PyObject *xobj, *tseq;
    double scale;
    int combine_max;
    fluence_model m;
    Py_ssize_t start, stop;

    if (!PyArg_ParseTuple(args, "Ow*Odpidddddd(nn)",
                          &xobj, &ab, &tseq, &scale, &combine_max,
                          &m.linear_only, &m.A, &m.x0, &m.dx, &m.alpha,
                          &m.half_well, &m.slope, &start, &stop))
        return NULL;
    if (PyObject_GetBuffer(xobj, &xb, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) {
        PyBuffer_Release(&ab);
        return NULL;
    }
    int kind, swap;
    if (parse_format(xb.format, &kind, &swap) < 0) {
        PyErr_Format(PyExc_TypeError, "fluence buffer must hold float32 or float64, not '%s'",
                     xb.format ? xb.format : "B");
        goto fail;
    }
    Py_ssize_t itemsize = (kind == K_F4) ? 4 : 8;
    Py_ssize_t npix = xb.len / itemsize;
    PyObject *tfast = PySequence_Fast(tseq, "time factors must be a sequence");
    if (tfast == NULL) goto fail;
    Py_ssize_t nk = PySequence_Fast_GET_SIZE(tfast);
    double *T = PyMem_Malloc(sizeof(double) * (nk > 0 ? nk : 1));
    if (T == NULL) { Py_DECREF(tfast); PyErr_NoMemory(); goto fail; }
    for (Py_ssize_t k = 0; k < nk; k++) {
        T[k] = PyFloat_AsDouble(PySequence_Fast_GET_ITEM(tfast, k));
    }
    Py_DECREF(tfast);
    if (PyErr_Occurred()) { PyMem_Free(T); goto fail; }
    if (ab.len != (Py_ssize_t)sizeof(double) * npix * nk) {
        PyErr_Format(PyExc_ValueError,
                     "accumulator holds %zd bytes, expected %zd (float64, %zd planes of %zd pixels)",
                     ab.len, (Py_ssize_t)sizeof(double) * npix * nk, nk, npix);
        PyMem_Free(T);
        goto fail;
    }
    if (start < 0) start = 0;
    if (stop > npix) stop = npix;

    const unsigned char *xs = (const unsigned char *)xb.buf;
    double *acc = (double *)ab.buf;
    Py_ssize_t nonfinite = 0;
    uint64_t sum = 0;
    Py_BEGIN_ALLOW_THREADS
    if (kind == K_F4 && nk == 1 && !combine_max && !m.linear_only && m.half_well >= 0.0) {
        accumulate_f4_linear_first(xs, acc, start, stop, swap, scale, T[0], &m, &sum, &nonfinite);
    } else if (kind == K_F4) {
        if (swap) { ACCUMULATE_LOOP(load_f4, 1) } else { ACCUMULATE_LOOP(load_f4, 0) }
    } else {
        if (swap) { ACCUMULATE_LOOP(load_f8, 1) } else { ACCUMULATE_LOOP(load_f8, 0) }
    }
    while (sum >> 32) FOLD(sum);
    Py_END_ALLOW_THREADS
    PyMem_Free(T);
    PyBuffer_Release(&xb);
    PyBuffer_Release(&ab);
    return Py_BuildValue("nK", nonfinite, (unsigned long long)sum);

fail:
    PyBuffer_Release(&xb);
    PyBuffer_Release(&ab);
    return NULL;
}

/* FITS DATASUM: the 32-bit ones'-complement sum of the data block read as
 * big-endian unsigned words (FITS Standard 4.0, appendix J).  Trailing bytes
 * are padded with zeros, as the FITS block padding would be. */
static PyObject *
datasum(PyObject *self, PyObject *args)
{
    Py_buffer b;
    if (!PyArg_ParseTuple(args, "y*", &b)) return NULL;
    const unsigned char *p = (const unsigned char *)b.buf;
    Py_ssize_t nwords = b.len / 4, rem = b.len % 4;
    uint64_t sum = 0;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < nwords; i++) {
        const unsigned char *q = p + 4 * i;
        sum += ((uint64_t)q[0] << 24) | ((uint64_t)q[1] << 16) | ((uint64_t)q[2] << 8) | q[3];
        /* fold now and then so the 64-bit sum cannot overflow */
        if ((i & 0xFFFFFF) == 0xFFFFFF) sum = (sum & 0xFFFFFFFFu) + (sum >> 32);
    }
    if (rem) {
        uint32_t w = 0;
        for (Py_ssize_t j = 0; j < rem; j++) w |= (uint32_t)p[4 * nwords + j] << (24 - 8 * j);
        sum += w;
    }
    while (sum >> 32) sum = (sum & 0xFFFFFFFFu) + (sum >> 32);
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&b);
    return PyLong_FromUnsignedLongLong(sum);
}

/* ---- perscli measure: the exponential mixture through a tabulated PSF -------------------------- */

/* exp(x) for x <= 0 with IEEE add and multiply only, so that the loop calling it vectorises (libm's
 * exp is a call the compiler cannot unroll into vector lanes, and it was most of a fit's time).
 * Cody-Waite reduction x = n ln2 + r (|r| <= ln2/2; fdlibm's split of ln2, so n ln2_hi is exact),
 * a degree-13 Taylor polynomial (truncation 4e-18 relative, below half an ulp) and 2^n written into
 * the exponent bits (n read back from the bits of x log2e + 1.5 2^52, which rounds to an integer).
 * Within 2 ulp of libm's exp (tests/test_measure_kernel.py); 0 below -708, where exp < 3e-308.
 * It is exact in the sense that matters for the fits (NOTES section 4): not a table or a low-order
 * approximation.  The module is built with -std=c99, which turns FMA contraction off, so the vector
 * and scalar forms of this function give the same bits. */
static inline double
exp_nonpos(double x)
{
    const double shifter = 6755399441055744.0;             /* 1.5 * 2^52 */
    const double log2e = 1.4426950408889634074;
    const double ln2_hi = 6.93147180369123816490e-01;
    const double ln2_lo = 1.90821492927058770002e-10;
    const double xc = x < -708.0 ? -708.0 : x;
    const double t = xc * log2e + shifter;
    const double n = t - shifter;
    const double r = (xc - n * ln2_hi) - n * ln2_lo;
    double p = 1.0 / 6227020800.0;
    p = p * r + 1.0 / 479001600.0;
    p = p * r + 1.0 / 39916800.0;
    p = p * r + 1.0 / 3628800.0;
    p = p * r + 1.0 / 362880.0;
    p = p * r + 1.0 / 40320.0;
    p = p * r + 1.0 / 5040.0;
    p = p * r + 1.0 / 720.0;
    p = p * r + 1.0 / 120.0;
    p = p * r + 1.0 / 24.0;
    p = p * r + 1.0 / 6.0;
    p = p * r + 0.5;
    p = p * r + 1.0;
    p = p * r + 1.0;
    uint64_t tb;
    memcpy(&tb, &t, 8);
    const uint64_t eb = (tb - UINT64_C(0x4338000000000000) + 1023u) << 52;
    double scale;
    memcpy(&scale, &eb, 8);
    const double v = p * scale;
    return x < -708.0 ? 0.0 : v;
}

static PyObject *
exp_nonpos_py(PyObject *self, PyObject *args)
{
    Py_buffer xb, ob;
    if (!PyArg_ParseTuple(args, "y*w*", &xb, &ob)) return NULL;
    if (xb.len != ob.len || xb.len % sizeof(double)) {
        PyBuffer_Release(&xb); PyBuffer_Release(&ob);
        PyErr_SetString(PyExc_ValueError, "exp_nonpos: two float64 buffers of the same size");
        return NULL;
    }
    const double *x = (const double *)xb.buf;
    double *o = (double *)ob.buf;
    const Py_ssize_t n = xb.len / (Py_ssize_t)sizeof(double);
    for (Py_ssize_t i = 0; i < n; i++) o[i] = exp_nonpos(x[i] > 0.0 ? 0.0 : x[i]);
    PyBuffer_Release(&xb); PyBuffer_Release(&ob);
    Py_RETURN_NONE;
}

/* Number of Hessian sums gathered per frequency column (see expmix_eval), and of mixture
 * components (Hogg & Lang's exponential: 6; a constant so that their loop unrolls). */
#define NHESS 21
#define NCOMP 6

/* One row of the extended frequency grid: the fold of its columns [cx0, cx0 + half) into the
 * half-plane row `o` (rfft layout; split: real and imaginary planes of `plane` values per field),
 * and the Hessian sums per folded column.  Written as one loop over the columns with no branch
 * and no call, which the compiler vectorises; nfield and hess are constants in each of the three
 * instances below, so that each is a loop of its own. */
static inline __attribute__((always_inline)) void
expmix_row_body(Py_ssize_t half, Py_ssize_t plane, const int nfield, const int hess,
           const double *restrict kxs, const double *restrict trr, const double *restrict tri,
           const double *restrict pxs, double ky, double pyr, double pyi,
           const double *restrict p, const double *restrict f,
           double A, double B, double C, double flux, const double *restrict dp, const double *restrict ds,
           const double *restrict vr, const double *restrict vi, const double *restrict wcol,
           double *restrict o, double *restrict h)
{
    const double kyy = ky * ky;
    /* the planes of o and h never overlap: no dependence between columns */
#pragma GCC ivdep
    for (Py_ssize_t j = 0; j < half; j++) {
        const double kx = kxs[j], kxx = kx * kx, kxy = kx * ky;
        /* common = PSF x pixel transfer x the phase of the centre */
        const double pxr = pxs[2 * j], pxi = pxs[2 * j + 1];
        const double ph_r = pxr * pyr - pxi * pyi, ph_i = pxr * pyi + pxi * pyr;
        const double cr = trr[j] * ph_r - tri[j] * ph_i, ci = trr[j] * ph_i + tri[j] * ph_r;
        /* k^T C k with C the unit covariance of the mixture (component i: f_i C) */
        const double q = A * kxx + 2.0 * B * kxy + C * kyy;
        double s0 = 0.0, s1 = 0.0, s2 = 0.0;
        for (int i = 0; i < NCOMP; i++) {
            const double term = p[i] * exp_nonpos(-0.5 * f[i] * q);
            s0 += term;
            s1 += f[i] * term;
            s2 += f[i] * f[i] * term;
        }
        /* split layout: the real and imaginary planes of field f at o + 2 f plane and o + (2 f + 1) plane */
        const double mr = flux * s0 * cr, mi = flux * s0 * ci;
        if (nfield > 0) {
            o[j] += mr;
            o[plane + j] += mi;
        }
        if (nfield > 1) {
            /* d/dcx = -i kx M: the position parameters through dp (d centre / d parameter) */
            const double k0 = kx * dp[0] + ky * dp[2], k1 = kx * dp[1] + ky * dp[3];
            o[2 * plane + j] += k0 * mi;
            o[3 * plane + j] -= k0 * mr;
            o[4 * plane + j] += k1 * mi;
            o[5 * plane + j] -= k1 * mr;
            /* d/dC_c = -flux s1 / 2 Q_c common with Q = (kx^2, 2 kx ky, ky^2); shape parameters through ds */
            const double w = -0.5 * flux * s1;
            const double q0 = w * (kxx * ds[0] + 2.0 * kxy * ds[3] + kyy * ds[6]);
            const double q1 = w * (kxx * ds[1] + 2.0 * kxy * ds[4] + kyy * ds[7]);
            const double q2 = w * (kxx * ds[2] + 2.0 * kxy * ds[5] + kyy * ds[8]);
            o[6 * plane + j] += q0 * cr;
            o[7 * plane + j] += q0 * ci;
            o[8 * plane + j] += q1 * cr;
            o[9 * plane + j] += q1 * ci;
            o[10 * plane + j] += q2 * cr;
            o[11 * plane + j] += q2 * ci;
            o[12 * plane + j] += s0 * cr;
            o[13 * plane + j] += s0 * ci;
        }
        if (hess) {
            /* Re[second derivative x conj(V)], V the transform of the weighted residual: R and I are
             * the real and imaginary parts of common x conj(V), times the column's weight in the
             * half plane (1 for the DC and Nyquist columns, 2 for the others) */
            const double R = wcol[j] * (cr * vr[j] + ci * vi[j]);
            const double Im = wcol[j] * (ci * vr[j] - cr * vi[j]);
            const double Q0 = kxx, Q1 = 2.0 * kxy, Q2 = kyy;
            const double s0R = s0 * R, s1I = s1 * Im, s2R = s2 * R, s1R = s1 * R, s0I = s0 * Im;
            h[0 * half + j] += kxx * s0R;
            h[1 * half + j] += kxy * s0R;
            h[2 * half + j] += kyy * s0R;
            h[3 * half + j] += Q0 * kx * s1I;
            h[4 * half + j] += Q1 * kx * s1I;
            h[5 * half + j] += Q2 * kx * s1I;
            h[6 * half + j] += Q0 * ky * s1I;
            h[7 * half + j] += Q1 * ky * s1I;
            h[8 * half + j] += Q2 * ky * s1I;
            h[9 * half + j] += Q0 * Q0 * s2R;
            h[10 * half + j] += Q0 * Q1 * s2R;
            h[11 * half + j] += Q0 * Q2 * s2R;
            h[12 * half + j] += Q1 * Q1 * s2R;
            h[13 * half + j] += Q1 * Q2 * s2R;
            h[14 * half + j] += Q2 * Q2 * s2R;
            h[15 * half + j] += kx * s0I;
            h[16 * half + j] += ky * s0I;
            h[17 * half + j] += Q0 * s1R;
            h[18 * half + j] += Q1 * s1R;
            h[19 * half + j] += Q2 * s1R;
            h[20 * half + j] += s0R;
        }
    }
}

#define EXPMIX_ROW_ARGS Py_ssize_t half, Py_ssize_t plane, const double *restrict kxs, \
    const double *restrict trr, const double *restrict tri, const double *restrict pxs, double ky, double pyr, \
    double pyi, const double *restrict p, const double *restrict f, double A, double B, double C, double flux, \
    const double *restrict dp, const double *restrict ds, const double *restrict vr, const double *restrict vi, \
    const double *restrict wcol, double *restrict o, double *restrict h
#define EXPMIX_ROW_PASS kxs, trr, tri, pxs, ky, pyr, pyi, p, f, A, B, C, flux, dp, ds, vr, vi, wcol, o, h

PERSCLI_CLONES static void
expmix_row_model(EXPMIX_ROW_ARGS) { expmix_row_body(half, plane, 1, 0, EXPMIX_ROW_PASS); }

PERSCLI_CLONES static void
expmix_row_jac(EXPMIX_ROW_ARGS) { expmix_row_body(half, plane, 7, 0, EXPMIX_ROW_PASS); }

PERSCLI_CLONES static void
expmix_row_hess(EXPMIX_ROW_ARGS) { expmix_row_body(half, plane, 7, 1, EXPMIX_ROW_PASS); }

PERSCLI_CLONES static void
expmix_row_hess_only(EXPMIX_ROW_ARGS) { expmix_row_body(half, plane, 0, 1, EXPMIX_ROW_PASS); }

/* The exponential mixture through a tabulated PSF, in Fourier space, folded.
 *
 * For every frequency of the extended (alias x L)^2 grid (centred order) whose folded column lies
 * in the half plane [0, L/2], evaluates the mixture's transform times the PSF transfer and the
 * phase of the centre, and adds it into the folded half-plane spectrum spec[0] (rfft layout, L x
 * (L/2 + 1), complex; `work` holds the same in split real/imaginary planes while it is summed, and
 * with v the residual's spectrum split likewise: 2 (nfield + 1) planes).  With nfield = 7 it also adds the derivatives with respect to six parameters: two of
 * position, mapped from the centre (cx, cy) by dp (row-major 2x2, d centre_a / d param_j), three of
 * shape, mapped from the unit covariance (Cxx, Cxy, Cyy) by ds (row-major 3x3, d C_c / d param_j),
 * and the flux.  With a residual transform (v: complex L x (L/2 + 1), the rfft2 of the weighted
 * residual on the same grid) it returns the 21 sums from which the caller builds the second-order
 * term of the Hessian (sum over pixels of residual x second derivative of the model) by Parseval,
 * without any inverse transform: entries 0-2 d2/dc dc, 3-8 d2/dc dC, 9-14 d2/dC dC, 15-16 d2/dflux
 * dc, 17-19 d2/dflux dC, 20 the residual's overlap with the model (all before the factors of flux,
 * -1/2, 1/4 and 1/L^2 that the caller applies).
 */
static PyObject *
expmix_eval(PyObject *self, PyObject *args)
{
    Py_buffer sb, ob, trb, tib, kb, pxb, pyb, pb, fb, wb;
    PyObject *vobj, *hobj;
    int L, M, nfield;
    double A, B, C, flux;
    double dp[4], ds[9];
    if (!PyArg_ParseTuple(args, "w*w*y*y*y*y*y*y*y*iii(dddd)(dddd)(ddddddddd)OOy*",
                          &sb, &ob, &trb, &tib, &kb, &pxb, &pyb, &pb, &fb, &L, &M, &nfield,
                          &A, &B, &C, &flux, &dp[0], &dp[1], &dp[2], &dp[3],
                          &ds[0], &ds[1], &ds[2], &ds[3], &ds[4], &ds[5], &ds[6], &ds[7], &ds[8],
                          &vobj, &hobj, &wb))
        return NULL;
    Py_buffer vb = {0}, hb = {0};
    int have_v = 0, have_h = 0;
    PyObject *result = NULL;
    const Py_ssize_t big = (Py_ssize_t)L * M, half = L / 2 + 1, plane = (Py_ssize_t)L * half;
    if (vobj != Py_None) {
        if (PyObject_GetBuffer(vobj, &vb, PyBUF_C_CONTIGUOUS) < 0) goto done;
        if (PyObject_GetBuffer(hobj, &hb, PyBUF_C_CONTIGUOUS | PyBUF_WRITABLE) < 0) {
            PyBuffer_Release(&vb); goto done;
        }
        have_v = 1;
        have_h = 1;
    }
    if ((nfield != 1 && nfield != 7) || L < 2 || L % 2 || M < 1 ||
        trb.len != (Py_ssize_t)sizeof(double) * big * big || tib.len != trb.len ||
        kb.len != (Py_ssize_t)sizeof(double) * big ||
        pxb.len != (Py_ssize_t)sizeof(double) * 2 * big || pyb.len != pxb.len ||
        ob.len < (Py_ssize_t)sizeof(double) * 2 * (nfield + (have_v ? 1 : 0)) * plane ||
        sb.len != (Py_ssize_t)sizeof(double) * 2 * nfield * plane || pb.len != fb.len ||
        pb.len != (Py_ssize_t)sizeof(double) * NCOMP ||
        wb.len != (Py_ssize_t)sizeof(double) * half ||
        (have_v && nfield != 7) ||
        (have_v && (vb.len != (Py_ssize_t)sizeof(double) * 2 * plane ||
                    hb.len != (Py_ssize_t)sizeof(double) * NHESS * half))) {
        PyErr_SetString(PyExc_ValueError, "expmix_eval: buffer sizes do not match L, alias and the field count");
        goto release;
    }
    {
        const double *trr = (const double *)trb.buf, *tri = (const double *)tib.buf;
        const double *k = (const double *)kb.buf;
        const double *px = (const double *)pxb.buf, *py = (const double *)pyb.buf;
        const double *p = (const double *)pb.buf, *f = (const double *)fb.buf, *wcol = (const double *)wb.buf;
        double *out = (double *)ob.buf;
        /* the residual's spectrum (complex, as numpy's rfft2 gives it) split into planes after the
         * fields' in the work space, so that the loop over columns reads it with unit stride */
        double *vr = have_v ? out + 2 * nfield * plane : NULL, *vi = have_v ? out + (2 * nfield + 1) * plane : NULL;
        const double *v = have_v ? (const double *)vb.buf : NULL;
        double *h = have_h ? (double *)hb.buf : NULL;
        Py_BEGIN_ALLOW_THREADS
        memset(out, 0, sizeof(double) * 2 * nfield * plane);
        if (have_v) {
            for (Py_ssize_t i = 0; i < plane; i++) {
                vr[i] = v[2 * i];
                vi[i] = v[2 * i + 1];
            }
        }
        if (h) memset(h, 0, sizeof(double) * NHESS * half);
        for (Py_ssize_t cy = 0; cy < big; cy++) {
            const Py_ssize_t row = cy % L;
            for (Py_ssize_t cx0 = 0; cx0 < big; cx0 += L) {
                /* the columns of this block that fold into the half plane: [cx0, cx0 + half) */
                const double *kxs = k + cx0, *rr = trr + cy * big + cx0, *ri = tri + cy * big + cx0;
                const double *pxs = px + 2 * cx0, ky = k[cy], pyr = py[2 * cy], pyi = py[2 * cy + 1];
                double *o = out + row * half;
                if (have_v)
                    expmix_row_hess(half, plane, kxs, rr, ri, pxs, ky, pyr, pyi, p, f, A, B, C, flux, dp, ds,
                                    vr + row * half, vi + row * half, wcol, o, h);
                else if (nfield == 7)
                    expmix_row_jac(half, plane, kxs, rr, ri, pxs, ky, pyr, pyi, p, f, A, B, C, flux, dp, ds,
                                   NULL, NULL, wcol, o, h);
                else
                    expmix_row_model(half, plane, kxs, rr, ri, pxs, ky, pyr, pyi, p, f, A, B, C, flux, dp, ds,
                                     NULL, NULL, wcol, o, h);
            }
        }
        /* the split planes into the interleaved complex spectra numpy's irfft2 reads */
        double *spec = (double *)sb.buf;
        for (int fld = 0; fld < nfield; fld++) {
            const double *re = out + 2 * fld * plane, *im = out + (2 * fld + 1) * plane;
            double *dst = spec + 2 * fld * plane;
            for (Py_ssize_t i = 0; i < plane; i++) {
                dst[2 * i] = re[i];
                dst[2 * i + 1] = im[i];
            }
        }
        Py_END_ALLOW_THREADS
    }
    result = Py_None;
    Py_INCREF(result);
release:
    if (have_v) { PyBuffer_Release(&vb); PyBuffer_Release(&hb); }
done:
    PyBuffer_Release(&sb); PyBuffer_Release(&ob); PyBuffer_Release(&trb); PyBuffer_Release(&tib); PyBuffer_Release(&kb);
    PyBuffer_Release(&pxb); PyBuffer_Release(&pyb); PyBuffer_Release(&pb); PyBuffer_Release(&fb);
    PyBuffer_Release(&wb);
    return result;
}


/* expmix_batch(spec, work, transfers, k, L, M, nfield, params, phase_x, phase_y, resid, hess, wcol): expmix_eval
 * for S stamps of one size at once (one galaxy on S frames, each with its own PSF transfer).
 *   spec:      complex, S x nfield x L x (L/2 + 1), out
 *   work:      doubles, 2 (nfield + 1) L (L/2 + 1), scratch
 *   transfers: sequence of S pairs (tr_re, tr_im), each (L M)^2 doubles
 *   params:    S rows of 17 doubles: Cxx, Cxy, Cyy, flux, dpos (4, row-major), dshape (9, row-major)
 *   phase_x, phase_y: complex, S x (L M)
 *   resid:     None, or complex S x L x (L/2 + 1) (the weighted residuals' rfft2): then hess (S x 21 doubles)
 *              receives each stamp's Hessian sums (summed over columns), as expmix_eval's caller sums them
 *   nfield:    1 or 7; or 0 with resid: the Hessian sums only (spec empty), the second-order term at a point
 *              whose model and derivatives are known already */
static PyObject *
expmix_batch(PyObject *self, PyObject *args)
{
    Py_buffer sb, ob, kb, pb, pxb, pyb, wb, mpb, mfb;
    PyObject *transfers, *robj, *hobj;
    int L, M, nfield;
    if (!PyArg_ParseTuple(args, "w*w*Oy*iiiy*y*y*OOy*y*y*", &sb, &ob, &transfers, &kb, &L, &M, &nfield, &pb, &pxb,
                          &pyb, &robj, &hobj, &wb, &mpb, &mfb))
        return NULL;
    PyObject *result = NULL, *seq = NULL;
    Py_buffer rb = {0}, hb = {0};
    int have_r = 0;
    Py_buffer *trs = NULL;
    Py_ssize_t ntr = 0;
    const Py_ssize_t big = (Py_ssize_t)L * M, half = L / 2 + 1, plane = (Py_ssize_t)L * half;
    const Py_ssize_t S = pb.len / (Py_ssize_t)(17 * sizeof(double));
    if (robj != Py_None) {
        if (PyObject_GetBuffer(robj, &rb, PyBUF_C_CONTIGUOUS) < 0) goto release;
        if (PyObject_GetBuffer(hobj, &hb, PyBUF_C_CONTIGUOUS | PyBUF_WRITABLE) < 0) { PyBuffer_Release(&rb); goto release; }
        have_r = 1;
    }
    seq = PySequence_Fast(transfers, "expmix_batch: transfers must be a sequence of (tr_re, tr_im) pairs");
    if (!seq) goto release;
    if (PySequence_Fast_GET_SIZE(seq) != S) {
        PyErr_SetString(PyExc_ValueError, "expmix_batch: one transfer pair per stamp");
        goto release;
    }
    trs = PyMem_Calloc(2 * (size_t)(S ? S : 1), sizeof(Py_buffer));
    if (!trs) { PyErr_NoMemory(); goto release; }
    for (Py_ssize_t i = 0; i < S; i++) {
        PyObject *pair = PySequence_Fast_GET_ITEM(seq, i);
        PyObject *re, *im;
        if (!PyArg_ParseTuple(pair, "OO", &re, &im)) goto release;
        if (PyObject_GetBuffer(re, &trs[2 * i], PyBUF_C_CONTIGUOUS) < 0) goto release;
        ntr = 2 * i + 1;
        if (PyObject_GetBuffer(im, &trs[2 * i + 1], PyBUF_C_CONTIGUOUS) < 0) goto release;
        ntr = 2 * i + 2;
        if (trs[2 * i].len != (Py_ssize_t)sizeof(double) * big * big || trs[2 * i + 1].len != trs[2 * i].len) {
            PyErr_SetString(PyExc_ValueError, "expmix_batch: a transfer table's size does not match L and the alias");
            goto release;
        }
    }
    if ((nfield != 1 && nfield != 7 && !(nfield == 0 && have_r)) || L < 2 || L % 2 || M < 1 ||
        pb.len != S * 17 * (Py_ssize_t)sizeof(double) ||
        kb.len != (Py_ssize_t)sizeof(double) * big ||
        pxb.len != (Py_ssize_t)sizeof(double) * 2 * big * S || pyb.len != pxb.len ||
        sb.len != (Py_ssize_t)sizeof(double) * 2 * nfield * plane * S ||
        ob.len < (Py_ssize_t)sizeof(double) * 2 * (nfield + 1) * plane ||
        wb.len != (Py_ssize_t)sizeof(double) * half ||
        mpb.len != (Py_ssize_t)sizeof(double) * NCOMP || mfb.len != mpb.len ||
        (have_r && (nfield == 1 || rb.len != (Py_ssize_t)sizeof(double) * 2 * plane * S ||
                    hb.len != (Py_ssize_t)sizeof(double) * NHESS * S))) {
        PyErr_SetString(PyExc_ValueError, "expmix_batch: buffer sizes do not match L, alias, stamps and fields");
        goto release;
    }
    {
        const double *k = (const double *)kb.buf, *par = (const double *)pb.buf, *wcol = (const double *)wb.buf;
        const double *P_EXP_C = (const double *)mpb.buf, *F_EXP_C = (const double *)mfb.buf;
        const double *pxall = (const double *)pxb.buf, *pyall = (const double *)pyb.buf;
        const double *rall = have_r ? (const double *)rb.buf : NULL;
        double *hall = have_r ? (double *)hb.buf : NULL;
        double *out = (double *)ob.buf, *specall = (double *)sb.buf;
        double *hrow = NULL;
        if (have_r) {
            hrow = PyMem_Malloc(sizeof(double) * NHESS * half);
            if (!hrow) { PyErr_NoMemory(); goto release; }
        }
        Py_BEGIN_ALLOW_THREADS
        for (Py_ssize_t st = 0; st < S; st++) {
            const double *p = par + 17 * st;
            const double *trr = (const double *)trs[2 * st].buf, *tri = (const double *)trs[2 * st + 1].buf;
            const double *px = pxall + 2 * big * st, *py = pyall + 2 * big * st;
            double *vr = have_r ? out + 2 * nfield * plane : NULL, *vi = have_r ? out + (2 * nfield + 1) * plane : NULL;
            memset(out, 0, sizeof(double) * 2 * nfield * plane);
            if (have_r) {
                const double *v = rall + 2 * plane * st;
                for (Py_ssize_t i = 0; i < plane; i++) {
                    vr[i] = v[2 * i];
                    vi[i] = v[2 * i + 1];
                }
                memset(hrow, 0, sizeof(double) * NHESS * half);
            }
            for (Py_ssize_t cy = 0; cy < big; cy++) {
                const Py_ssize_t row = cy % L;
                for (Py_ssize_t cx0 = 0; cx0 < big; cx0 += L) {
                    const double *kxs = k + cx0, *rr = trr + cy * big + cx0, *ri = tri + cy * big + cx0;
                    const double *pxs = px + 2 * cx0, ky = k[cy], pyr = py[2 * cy], pyi = py[2 * cy + 1];
                    double *o = out + row * half;
                    if (have_r && nfield == 0)
                        expmix_row_hess_only(half, plane, kxs, rr, ri, pxs, ky, pyr, pyi, P_EXP_C, F_EXP_C, p[0],
                                             p[1], p[2], p[3], p + 4, p + 8, vr + row * half, vi + row * half, wcol,
                                             o, hrow);
                    else if (have_r)
                        expmix_row_hess(half, plane, kxs, rr, ri, pxs, ky, pyr, pyi, P_EXP_C, F_EXP_C, p[0], p[1],
                                        p[2], p[3], p + 4, p + 8, vr + row * half, vi + row * half, wcol, o, hrow);
                    else if (nfield == 7)
                        expmix_row_jac(half, plane, kxs, rr, ri, pxs, ky, pyr, pyi, P_EXP_C, F_EXP_C, p[0], p[1],
                                       p[2], p[3], p + 4, p + 8, NULL, NULL, wcol, o, NULL);
                    else
                        expmix_row_model(half, plane, kxs, rr, ri, pxs, ky, pyr, pyi, P_EXP_C, F_EXP_C, p[0], p[1],
                                         p[2], p[3], p + 4, p + 8, NULL, NULL, wcol, o, NULL);
                }
            }
            double *spec = specall + 2 * nfield * plane * st;
            for (int fld = 0; fld < nfield; fld++) {
                const double *re = out + 2 * fld * plane, *im = out + (2 * fld + 1) * plane;
                double *dst = spec + 2 * fld * plane;
                for (Py_ssize_t i = 0; i < plane; i++) {
                    dst[2 * i] = re[i];
                    dst[2 * i + 1] = im[i];
                }
            }
            if (have_r) {
                double *h = hall + NHESS * st;
                for (int q = 0; q < NHESS; q++) {
                    double acc = 0.0;
                    for (Py_ssize_t j = 0; j < half; j++) acc += hrow[q * half + j];
                    h[q] = acc;
                }
            }
        }
        Py_END_ALLOW_THREADS
        PyMem_Free(hrow);
    }
    result = Py_None;
    Py_INCREF(result);
release:
    if (trs) {
        for (Py_ssize_t i = 0; i < ntr; i++) PyBuffer_Release(&trs[i]);
        PyMem_Free(trs);
    }
    Py_XDECREF(seq);
    if (have_r) { PyBuffer_Release(&rb); PyBuffer_Release(&hb); }
    PyBuffer_Release(&sb); PyBuffer_Release(&ob); PyBuffer_Release(&kb); PyBuffer_Release(&pb);
    PyBuffer_Release(&pxb); PyBuffer_Release(&pyb); PyBuffer_Release(&wb); PyBuffer_Release(&mpb);
    PyBuffer_Release(&mfb);
    return result;
}

/* ---- perscli render: objects through a tabulated PSF, folded -------------------------------------- */

/* One row of the extended frequency grid for one object: the columns [0, half) of each block of L
 * (those that fold into the half plane) times the PSF transfer, the object's transform and the phase of
 * its centre, added into the folded row (split real and imaginary planes).  galaxy: the exponential's
 * transform 1/(1 + k^T C k)^(3/2), C = (a, b; b, c); else a point. */
PERSCLI_CLONES static void
fold_row(Py_ssize_t half, Py_ssize_t L, Py_ssize_t big, const double *restrict kxs, const double *restrict trr,
         const double *restrict tri, const double *restrict pxr, const double *restrict pxi, double ky, double pyr,
         double pyi, double a, double b, double c, int galaxy, double *restrict ore, double *restrict oim)
{
    const double kyy = c * ky * ky, kyb = 2.0 * b * ky;
    for (Py_ssize_t cx0 = 0; cx0 < big; cx0 += L) {
#pragma GCC ivdep
        for (Py_ssize_t j = 0; j < half; j++) {
            const Py_ssize_t x = cx0 + j;
            const double kx = kxs[x];
            double g = 1.0;
            if (galaxy) {
                const double s = 1.0 + a * kx * kx + kyb * kx + kyy;
                g = 1.0 / (s * sqrt(s));
            }
            /* phase of the centre: exp(-i kx dx) exp(-i ky dy) */
            const double phr = pxr[x] * pyr - pxi[x] * pyi, phi = pxr[x] * pyi + pxi[x] * pyr;
            const double vr = g * (trr[x] * phr - tri[x] * phi), vi = g * (trr[x] * phi + tri[x] * phr);
            ore[j] += vr;
            oim[j] += vi;
        }
    }
}

/* fold_objects(out, work, tr_re, tr_im, k, L, M, params): the folded half-plane spectra of B objects of one
 * stamp size L through one PSF transfer (tabulated on the extended (L M)^2 grid, centred order), into out
 * (complex, B x L x (L/2 + 1), rfft layout: irfft2 gives each stamp, centred at index L/2 after a shift).
 * params: B rows of (dx, dy, a, b, c, galaxy): the sub-pixel offset of the centre, the exponential's
 * covariance form in pixel^2 (unused for a point), 1 for a galaxy.  work: 2 (L M + L (L/2 + 1)) doubles. */
static PyObject *
fold_objects(PyObject *self, PyObject *args)
{
    Py_buffer ob, wb, trb, tib, kb, pb;
    int L, M;
    if (!PyArg_ParseTuple(args, "w*w*y*y*y*iiy*", &ob, &wb, &trb, &tib, &kb, &L, &M, &pb))
        return NULL;
    PyObject *result = NULL;
    const Py_ssize_t big = (Py_ssize_t)L * M, half = L / 2 + 1, plane = (Py_ssize_t)L * half;
    const Py_ssize_t nobj = pb.len / (Py_ssize_t)(6 * sizeof(double));
    if (L < 2 || L % 2 || M < 1 || M % 2 && M != 1 || pb.len != nobj * 6 * (Py_ssize_t)sizeof(double) ||
        trb.len != (Py_ssize_t)sizeof(double) * big * big || tib.len != trb.len ||
        kb.len != (Py_ssize_t)sizeof(double) * big ||
        ob.len != (Py_ssize_t)sizeof(double) * 2 * nobj * plane ||
        wb.len < (Py_ssize_t)sizeof(double) * 2 * (2 * big + plane)) {
        PyErr_SetString(PyExc_ValueError, "fold_objects: buffer sizes do not match L, the alias and the objects");
        goto release;
    }
    {
        const double *trr = (const double *)trb.buf, *tri = (const double *)tib.buf, *k = (const double *)kb.buf;
        const double *par = (const double *)pb.buf;
        double *out = (double *)ob.buf, *w = (double *)wb.buf;
        double *pxr = w, *pxi = w + big, *pyr = w + 2 * big, *pyi = w + 3 * big;
        double *ore = w + 4 * big, *oim = ore + plane;
        Py_BEGIN_ALLOW_THREADS
        for (Py_ssize_t o = 0; o < nobj; o++) {
            const double *p = par + 6 * o;
            for (Py_ssize_t j = 0; j < big; j++) {
                pxr[j] = cos(k[j] * p[0]);
                pxi[j] = -sin(k[j] * p[0]);
                pyr[j] = cos(k[j] * p[1]);
                pyi[j] = -sin(k[j] * p[1]);
            }
            memset(ore, 0, sizeof(double) * 2 * plane);
            for (Py_ssize_t cy = 0; cy < big; cy++) {
                const Py_ssize_t row = cy % L;
                fold_row(half, L, big, k, trr + cy * big, tri + cy * big, pxr, pxi, k[cy], pyr[cy], pyi[cy],
                         p[2], p[3], p[4], p[5] != 0.0, ore + row * half, oim + row * half);
            }
            double *dst = out + 2 * o * plane;
            for (Py_ssize_t i = 0; i < plane; i++) {
                dst[2 * i] = ore[i];
                dst[2 * i + 1] = oim[i];
            }
        }
        Py_END_ALLOW_THREADS
    }
    result = Py_None;
    Py_INCREF(result);
release:
    PyBuffer_Release(&ob); PyBuffer_Release(&wb); PyBuffer_Release(&trb); PyBuffer_Release(&tib);
    PyBuffer_Release(&kb); PyBuffer_Release(&pb);
    return result;
}

/* ---- interpixel capacitance: a 3x3 correlation ------------------------------------------------ */

/* out[p, y, x] = sum over j, i of k[j][i] * x[p, y + j - 1, x + i - 1], zero outside each ny x nx plane:
 * scipy.ndimage.correlate(x, k[None], mode='constant', cval=0) for float64, bit for bit.  As ndimage
 * does, weights with |k| <= DBL_EPSILON are left out and the others are added in row-major order into
 * a sum that starts at 0 (a term outside the plane is 0 * k, which changes no sum).  The interior rows
 * take a branch-free loop the compiler vectorises; the GIL is released, so threads over exposures run
 * in parallel (ndimage holds it). */
static void
correlate_plane(const double *x, double *out, Py_ssize_t ny, Py_ssize_t nx, const double *k, const int *use)
{
    for (Py_ssize_t y = 0; y < ny; y++) {
        double *o = out + y * nx;
        const double *rows[3];
        for (int j = 0; j < 3; j++) {
            Py_ssize_t yy = y + j - 1;
            rows[j] = (yy >= 0 && yy < ny) ? x + yy * nx : NULL;
        }
        /* edge columns (and any column) in the general form */
        Py_ssize_t edges[2] = {0, nx - 1};
        for (int e = 0; e < (nx > 1 ? 2 : 1); e++) {
            Py_ssize_t c = edges[e];
            double acc = 0.0;
            for (int j = 0; j < 3; j++) {
                for (int i = 0; i < 3; i++) {
                    if (!use[3 * j + i]) continue;
                    Py_ssize_t cc = c + i - 1;
                    double v = (rows[j] != NULL && cc >= 0 && cc < nx) ? rows[j][cc] : 0.0;
                    acc += v * k[3 * j + i];
                }
            }
            o[c] = acc;
        }
        if (nx < 3) continue;
        if (rows[0] != NULL && rows[2] != NULL && use[0] && use[1] && use[2] && use[3] && use[4] && use[5]
            && use[6] && use[7] && use[8]) {
            const double *r0 = rows[0], *r1 = rows[1], *r2 = rows[2];
            const double k0 = k[0], k1 = k[1], k2 = k[2], k3 = k[3], k4 = k[4], k5 = k[5], k6 = k[6], k7 = k[7],
                         k8 = k[8];
            for (Py_ssize_t c = 1; c < nx - 1; c++) {
                double acc = 0.0;
                acc += r0[c - 1] * k0; acc += r0[c] * k1; acc += r0[c + 1] * k2;
                acc += r1[c - 1] * k3; acc += r1[c] * k4; acc += r1[c + 1] * k5;
                acc += r2[c - 1] * k6; acc += r2[c] * k7; acc += r2[c + 1] * k8;
                o[c] = acc;
            }
        } else {
            for (Py_ssize_t c = 1; c < nx - 1; c++) {
                double acc = 0.0;
                for (int j = 0; j < 3; j++) {
                    for (int i = 0; i < 3; i++) {
                        if (!use[3 * j + i]) continue;
                        double v = rows[j] != NULL ? rows[j][c + i - 1] : 0.0;
                        acc += v * k[3 * j + i];
                    }
                }
                o[c] = acc;
            }
        }
    }
}

static PyObject *
correlate3x3(PyObject *self, PyObject *args)
{
    Py_buffer xb, ob, kb;
    Py_ssize_t nplanes, ny, nx;
    if (!PyArg_ParseTuple(args, "y*w*y*(nnn)", &xb, &ob, &kb, &nplanes, &ny, &nx)) return NULL;
    PyObject *result = NULL;
    Py_ssize_t n = nplanes * ny * nx;
    if (nplanes < 0 || ny < 0 || nx < 0 || xb.len != (Py_ssize_t)sizeof(double) * n
        || ob.len != xb.len || kb.len != (Py_ssize_t)sizeof(double) * 9) {
        PyErr_SetString(PyExc_ValueError, "correlate3x3: x and out must hold nplanes x ny x nx float64, k 9 float64");
        goto done;
    }
    if (xb.buf == ob.buf && n > 0) {
        PyErr_SetString(PyExc_ValueError, "correlate3x3: out must not be x");
        goto done;
    }
    const double *k = (const double *)kb.buf;
    int use[9];
    for (int q = 0; q < 9; q++) use[q] = fabs(k[q]) > DBL_EPSILON;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t p = 0; p < nplanes; p++)
        correlate_plane((const double *)xb.buf + p * ny * nx, (double *)ob.buf + p * ny * nx, ny, nx, k, use);
    Py_END_ALLOW_THREADS
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&xb); PyBuffer_Release(&ob); PyBuffer_Release(&kb);
    return result;
}

/* ---- stamps added into an image ----------------------------------------------------------------- */

/* Add a run of stamps into an image (and the stars' into a second one), one stamp after the other in
 * the given order, as render's Python loop did: image[y0 + r, x0 + c] += flux * s[(r + h) % n, (c + h) % n]
 * with h = n / 2 (the stamp as the inverse FFT leaves it, its centre at [0, 0]: np.roll by n / 2 folded
 * into the indexing), clipped to the image.  The product and the sum are two roundings, as in numpy
 * (c99 forbids contracting them into a fused multiply-add): the same bits. */
static PyObject *
add_stamps(PyObject *self, PyObject *args)
{
    Py_buffer ib, sb, gb, slb, xb, yb, fb, stb;
    PyObject *groups, *starobj;
    Py_ssize_t ny, nx, xmin, ymin;
    if (!PyArg_ParseTuple(args, "w*O(nnnn)Oy*y*y*y*y*y*", &ib, &starobj, &ny, &nx, &xmin, &ymin, &groups,
                          &gb, &slb, &xb, &yb, &fb, &stb))
        return NULL;
    PyObject *result = NULL, *seq = NULL;
    Py_buffer *gbufs = NULL;
    Py_ssize_t ng = 0, nopen = 0;
    int have_star = 0;
    sb.buf = NULL;
    const Py_ssize_t nobj = fb.len / (Py_ssize_t)sizeof(double);
    if (ny < 0 || nx < 0 || ib.len != (Py_ssize_t)sizeof(double) * ny * nx ||
        fb.len != nobj * (Py_ssize_t)sizeof(double) || gb.len != nobj * (Py_ssize_t)sizeof(int64_t) ||
        slb.len != gb.len || xb.len != gb.len || yb.len != gb.len || stb.len != nobj) {
        PyErr_SetString(PyExc_ValueError, "add_stamps: image is not ny x nx float64, or the per-object arrays differ "
                        "in length");
        goto release;
    }
    if (starobj != Py_None) {
        if (PyObject_GetBuffer(starobj, &sb, PyBUF_WRITABLE | PyBUF_C_CONTIGUOUS) < 0) goto release;
        have_star = 1;
        if (sb.len != ib.len) {
            PyErr_SetString(PyExc_ValueError, "add_stamps: the stars' image differs from the image in size");
            goto release;
        }
    }
    seq = PySequence_Fast(groups, "add_stamps: groups must be a sequence of stamp arrays");
    if (seq == NULL) goto release;
    ng = PySequence_Fast_GET_SIZE(seq);
    gbufs = PyMem_Calloc(ng > 0 ? ng : 1, sizeof(Py_buffer));
    Py_ssize_t *side = PyMem_Calloc(ng > 0 ? ng : 1, sizeof(Py_ssize_t));
    Py_ssize_t *count = PyMem_Calloc(ng > 0 ? ng : 1, sizeof(Py_ssize_t));
    if (gbufs == NULL || side == NULL || count == NULL) { PyErr_NoMemory(); PyMem_Free(side); PyMem_Free(count);
                                                          goto release; }
    for (Py_ssize_t g = 0; g < ng; g++) {
        if (PyObject_GetBuffer(PySequence_Fast_GET_ITEM(seq, g), &gbufs[g], PyBUF_ND | PyBUF_C_CONTIGUOUS |
                               PyBUF_FORMAT) < 0) break;
        nopen++;
        Py_buffer *v = &gbufs[g];
        if (v->ndim != 3 || v->itemsize != (Py_ssize_t)sizeof(double) || v->shape[1] != v->shape[2] ||
            v->shape[1] < 2 || v->shape[1] % 2 || strcmp(v->format ? v->format : "B", "d") != 0) {
            PyErr_SetString(PyExc_ValueError, "add_stamps: each group must be a (B, n, n) float64 array, n even");
            break;
        }
        side[g] = v->shape[1];
        count[g] = v->shape[0];
    }
    if (nopen == ng && !PyErr_Occurred()) {
        const int64_t *grp = (const int64_t *)gb.buf, *slot = (const int64_t *)slb.buf;
        const int64_t *x0s = (const int64_t *)xb.buf, *y0s = (const int64_t *)yb.buf;
        const double *flux = (const double *)fb.buf;
        const unsigned char *isstar = (const unsigned char *)stb.buf;
        int bad = 0;
        for (Py_ssize_t o = 0; o < nobj; o++)
            if (grp[o] < 0 || grp[o] >= ng || slot[o] < 0 || slot[o] >= count[grp[o]]) bad = 1;
        if (bad) {
            PyErr_SetString(PyExc_ValueError, "add_stamps: an object's group or slot is out of range");
        } else {
            double *img = (double *)ib.buf, *simg = have_star ? (double *)sb.buf : NULL;
            Py_BEGIN_ALLOW_THREADS
            for (Py_ssize_t o = 0; o < nobj; o++) {
                const Py_ssize_t n = side[grp[o]], h = n / 2;
                const double *st = (const double *)gbufs[grp[o]].buf + slot[o] * n * n;
                const double f = flux[o];
                const Py_ssize_t x0 = x0s[o] - xmin, y0 = y0s[o] - ymin;
                const Py_ssize_t r0 = y0 < 0 ? -y0 : 0, r1 = y0 + n > ny ? ny - y0 : n;
                const Py_ssize_t c0 = x0 < 0 ? -x0 : 0, c1 = x0 + n > nx ? nx - x0 : n;
                double *other = (simg != NULL && isstar[o]) ? simg : NULL;
                /* columns [c0, cm) read the stamp's second half, [cm, c1) its first: no modulo per pixel */
                const Py_ssize_t cm = c1 < h ? c1 : (c0 > h ? c0 : h);
                for (Py_ssize_t r = r0; r < r1; r++) {
                    const double *src = st + ((r + h) % n) * n;
                    double *dst = img + (y0 + r) * nx + x0;
                    const double *lo = src + h, *hi = src - h;
                    for (Py_ssize_t c = c0; c < cm; c++) dst[c] += lo[c] * f;
                    for (Py_ssize_t c = cm; c < c1; c++) dst[c] += hi[c] * f;
                    if (other != NULL) {
                        double *dst2 = other + (y0 + r) * nx + x0;
                        for (Py_ssize_t c = c0; c < cm; c++) dst2[c] += lo[c] * f;
                        for (Py_ssize_t c = cm; c < c1; c++) dst2[c] += hi[c] * f;
                    }
                }
            }
            Py_END_ALLOW_THREADS
            result = Py_None;
            Py_INCREF(result);
        }
    }
    PyMem_Free(side);
    PyMem_Free(count);
release:
    for (Py_ssize_t g = 0; g < nopen; g++) PyBuffer_Release(&gbufs[g]);
    PyMem_Free(gbufs);
    Py_XDECREF(seq);
    if (have_star) PyBuffer_Release(&sb);
    PyBuffer_Release(&ib); PyBuffer_Release(&gb); PyBuffer_Release(&slb); PyBuffer_Release(&xb);
    PyBuffer_Release(&yb); PyBuffer_Release(&fb); PyBuffer_Release(&stb);
    return result;
}

static PyMethodDef methods[] = {
    {"accumulate", accumulate, METH_VARARGS,
     "accumulate(x, acc, time_factors, scale, combine_max, linear_only, A, x0, dx, alpha,\n"
     "           half_well, slope, (start, stop)) -> (non-finite pixels, datasum)\n\n"
     "For each pixel i in [start, stop) of x (float32/float64, any byte order):\n"
     "F = law(scale * x[i]); acc[k, i] += T[k] * F (or max).  Non-finite x count as 0.\n"
     "datasum is the FITS ones'-complement sum of x's words read big-endian."},
    {"expmix_eval", expmix_eval, METH_VARARGS,
     "expmix_eval(spec, work, tr_re, tr_im, k, phase_x, phase_y, p, f, L, alias, nfield, (Cxx, Cxy, Cyy, flux),\n"
     "            dpos (4), dshape (9), v, hess, wcol): folded half-plane spectra of the\n"
     "exponential mixture through the PSF transfer (and 6 parameter derivatives with nfield=7); with\n"
     "v (the weighted residual's rfft2, complex) the 21 sums of the Hessian's second-order term into hess."},
    {"expmix_batch", expmix_batch, METH_VARARGS,
     "expmix_batch(spec, work, transfers, k, L, alias, nfield, params, phase_x, phase_y, resid, hess, wcol, p, f):\n"
     "expmix_eval for several stamps of one size, each with its own PSF transfer (one galaxy on several frames)."},
    {"fold_objects", fold_objects, METH_VARARGS,
     "fold_objects(out, work, tr_re, tr_im, k, L, alias, params): folded half-plane spectra of objects\n"
     "(points or exponentials, params rows dx, dy, a, b, c, galaxy) through a tabulated PSF transfer."},
    {"exp_nonpos", exp_nonpos_py, METH_VARARGS,
     "exp_nonpos(x, out): out = exp(min(x, 0)) with the fitter's vectorisable exp (float64 buffers)."},
    {"add_stamps", add_stamps, METH_VARARGS,
     "add_stamps(image, stars_or_None, (ny, nx, xmin, ymin), groups, group, slot, x0, y0, flux, is_star) -> None\n\n"
     "For each object o in order: image[y0-ymin+r, x0-xmin+c] += flux[o] * s[(r+n/2)%n, (c+n/2)%n] with\n"
     "s = groups[group[o]][slot[o]] (n x n, unrolled), clipped to the image; also into stars_or_None\n"
     "where is_star[o].  group, slot, x0, y0: int64; flux: float64; is_star: uint8."},
    {"correlate3x3", correlate3x3, METH_VARARGS,
     "correlate3x3(x, out, k, (nplanes, ny, nx)): out = the 3x3 correlation of each plane of x with k\n"
     "(float64, C order; zero outside each plane), as scipy.ndimage.correlate(x, k[None], mode='constant')."},
    {"datasum", datasum, METH_VARARGS,
     "datasum(buffer) -> int: FITS DATASUM of raw (on-disk) data bytes."},
    {NULL, NULL, 0, NULL}
};

static struct PyModuleDef moduledef = {
    PyModuleDef_HEAD_INIT, "_kernels", "Compiled hot loops of perscli.", -1, methods
};

PyMODINIT_FUNC
PyInit__kernels(void)
{
    return PyModule_Create(&moduledef);
}
