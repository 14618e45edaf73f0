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
    if (kind == K_F4) {
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

static PyMethodDef methods[] = {
    {"accumulate", accumulate, METH_VARARGS,
     "accumulate(x, acc, time_factors, scale, combine_max, linear_only, A, x0, dx, alpha,\n"
     "           half_well, slope, (start, stop)) -> (non-finite pixels, datasum)\n\n"
     "For each pixel i in [start, stop) of x (float32/float64, any byte order):\n"
     "F = law(scale * x[i]); acc[k, i] += T[k] * F (or max).  Non-finite x count as 0.\n"
     "datasum is the FITS ones'-complement sum of x's words read big-endian."},
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
