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
#include <complex.h>
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

/* The exponential mixture through a tabulated PSF, in Fourier space, folded.
 *
 * For every frequency of the extended (alias x L)^2 grid (centred order) whose
 * folded column lies in the half plane [0, L/2], evaluates the mixture's
 * transform times the PSF transfer and the phase of the centre, and adds it
 * (and, with jac, its derivatives in x, y, g1, g2, T, flux) into the folded
 * half-plane spectra out[field, row, col] (rfft layout, L x (L/2 + 1)).  One
 * pass, no temporaries: this is the inner loop of every fit.
 */
static PyObject *
expmix_fold(PyObject *self, PyObject *args)
{
    Py_buffer ob, tb, kb, pxb, pyb, pb, fb;
    int L, M, jac;
    double e1, e2, T, flux, d00, d01, d10, d11;
    if (!PyArg_ParseTuple(args, "w*y*y*y*y*y*y*iip(dddd)(dddd)",
                          &ob, &tb, &kb, &pxb, &pyb, &pb, &fb, &L, &M, &jac,
                          &e1, &e2, &T, &flux, &d00, &d01, &d10, &d11))
        return NULL;
    const Py_ssize_t big = (Py_ssize_t)L * M, half = L / 2 + 1;
    const int nfield = jac ? 7 : 1;
    PyObject *result = NULL;
    if (tb.len != (Py_ssize_t)sizeof(double complex) * big * big || kb.len != (Py_ssize_t)sizeof(double) * big ||
        pxb.len != (Py_ssize_t)sizeof(double complex) * big || pyb.len != (Py_ssize_t)sizeof(double complex) * big ||
        ob.len != (Py_ssize_t)sizeof(double complex) * nfield * L * half || pb.len != fb.len ||
        pb.len % sizeof(double)) {
        PyErr_SetString(PyExc_ValueError, "expmix_fold: buffer sizes do not match L, alias and the field count");
        goto done;
    }
    {
        const double complex *tr = (const double complex *)tb.buf;
        const double *k = (const double *)kb.buf;
        const double complex *px = (const double complex *)pxb.buf, *py = (const double complex *)pyb.buf;
        const double *p = (const double *)pb.buf, *f = (const double *)fb.buf;
        const int ncomp = (int)(pb.len / sizeof(double));
        double complex *out = (double complex *)ob.buf;
        const Py_ssize_t plane = (Py_ssize_t)L * half;
        Py_BEGIN_ALLOW_THREADS
        memset(out, 0, sizeof(double complex) * nfield * plane);
        for (Py_ssize_t cy = 0; cy < big; cy++) {
            const double ky = k[cy], kyy = ky * ky;
            const Py_ssize_t row = cy % L;
            const double complex pyv = py[cy];
            for (Py_ssize_t cx = 0; cx < big; cx++) {
                const Py_ssize_t col = cx % L;
                if (col >= half) continue;
                const double complex t = tr[cy * big + cx];
                if (t == 0.0) continue;
                const double kx = k[cx], kxx = kx * kx, kxy = kx * ky;
                const double base = (kxx + kyy) + e1 * (kxx - kyy) + 2.0 * e2 * kxy;
                const double q = 0.5 * T * base;
                double s0 = 0.0, s1 = 0.0;
                for (int i = 0; i < ncomp; i++) {
                    const double a = -0.5 * f[i] * q;
                    /* components are ordered by size: once one is below e^-45 (1e-20 of the
                     * total, far below the fit's 1e-10 tolerance), so are the wider ones */
                    if (a < -45.0) break;
                    const double term = p[i] * exp(a);
                    s0 += term;
                    s1 += f[i] * term;
                }
                const double complex common = t * pyv * px[cx];
                const double complex g = s0 * common;
                double complex *o = out + row * half + col;
                o[0] += flux * g;
                if (jac) {
                    const double complex fg = flux * g;
                    o[plane] += -I * kx * fg;
                    o[2 * plane] += -I * ky * fg;
                    const double complex dq = -0.5 * flux * s1 * common;
                    const double complex de1 = dq * (0.5 * T * (kxx - kyy));
                    const double complex de2 = dq * (T * kxy);
                    o[3 * plane] += de1 * d00 + de2 * d10;
                    o[4 * plane] += de1 * d01 + de2 * d11;
                    o[5 * plane] += dq * (0.5 * base);
                    o[6 * plane] += g;
                }
            }
        }
        Py_END_ALLOW_THREADS
    }
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&ob); PyBuffer_Release(&tb); PyBuffer_Release(&kb); PyBuffer_Release(&pxb);
    PyBuffer_Release(&pyb); PyBuffer_Release(&pb); PyBuffer_Release(&fb);
    return result;
}

static PyMethodDef methods[] = {
    {"accumulate", accumulate, METH_VARARGS,
     "accumulate(x, acc, time_factors, scale, combine_max, linear_only, A, x0, dx, alpha,\n"
     "           half_well, slope, (start, stop)) -> (non-finite pixels, datasum)\n\n"
     "For each pixel i in [start, stop) of x (float32/float64, any byte order):\n"
     "F = law(scale * x[i]); acc[k, i] += T[k] * F (or max).  Non-finite x count as 0.\n"
     "datasum is the FITS ones'-complement sum of x's words read big-endian."},
    {"expmix_fold", expmix_fold, METH_VARARGS,
     "expmix_fold(out, transfer, k, phase_x, phase_y, p, f, L, alias, jac, (e1, e2, T, flux),\n"
     "            (de1/dg1, de1/dg2, de2/dg1, de2/dg2)): folded half-plane spectra of the exponential\n"
     "mixture through the PSF transfer (and its 6 derivatives with jac)."},
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
