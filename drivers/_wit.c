/* drivers._frames.WitStream: the WitMotion parser (drivers/wit.py's WitParser) in C.
 *
 * The same stream semantics as the Python parser, the reference (docs/wire-formats.md): any
 * packet mix the device can be set to send, packets split across reads, garbage and resync;
 * the cycle rule (a cycle ends on a type wrap or on its learned closing type), the same
 * ImuSample frames and the same counters. The scaling of each field is not written here: the
 * divisors come from wit.PAYLOADS (the one table) when the stream is made.
 *
 *   WitStream(sample_type, slots, divisors, layout)
 *     sample_type: drivers.frames.ImuSample; slots: its 8 slot descriptors in the order
 *     make_sample fills them (wit._FILLS names them); divisors: (acc, gyro, temperature,
 *     angle, quaternion); layout: the packet's, from wit.py (read_layout)
 *   .feed(data, t_ns) -> list[ImuSample]   .flush() -> list[ImuSample]
 *   .counts -> (frames, bytes_in, bytes_skipped, checksum_errors, unknown_types, dropped)
 *   .errors() -> [stream offset of a checksum mismatch, ...] since the last call (<= 16)
 *   .pending -> bytes held for the next read
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

#include "_wit.h"

#define MAX_ERRORS 16
/* what each packet type is, by wit.py's table (init's layout): the kinds this file decodes */
enum { K_NONE, TIME, ACC, GYRO, ANGLE, MAG, QUAT, READBACK, N_KINDS };
enum { N_SLOTS = 8 };
enum { DIV_ACC, DIV_GYRO, DIV_TEMP, DIV_ANGLE, DIV_QUAT, N_DIVS };

typedef struct {
    int has_acc, has_gyro, has_temp, has_angle, has_mag, has_quat, has_time, time_valid;
    double acc[3], gyro[3], temp, angle[3], quat[4];
    long mag[3];
    int64_t time_ns;
} Cycle;

typedef struct {
    PyObject_HEAD
    PyObject *sample_type, *slots;
    double div[N_DIVS];
    unsigned char *buf; /* bytes not consumed yet */
    Py_ssize_t len, cap;
    long long base; /* stream offset of buf[0] */
    Cycle cycle;
    int last_type, cycle_max, closing_type;
    long long cycle_t_ns;
    long long frames, bytes_in, bytes_skipped, checksum_errors, unknown_types, dropped;
    long long errors[MAX_ERRORS];
    int n_errors, error_head;
    int header, packet_len, temp_word; /* the layout handed at init (wit.py's table) */
    unsigned char kind[256], known[256]; /* per type byte: its kind; whether it is known */
} WitStream;

static int16_t i16(const unsigned char *b) { return (int16_t)(b[0] | (b[1] << 8)); }

static void note_error(WitStream *s, long long offset)
{
    s->errors[s->error_head] = offset;
    s->error_head = (s->error_head + 1) % MAX_ERRORS;
    if (s->n_errors < MAX_ERRORS)
        s->n_errors++;
}

/* days since 1970-01-01 of a proleptic Gregorian date (H. Hinnant's days_from_civil) */
static long long days_from_civil(long long y, int m, int d)
{
    y -= m <= 2;
    long long era = (y >= 0 ? y : y - 399) / 400;
    long long yoe = y - era * 400;
    long long doy = (153 * (m + (m > 2 ? -3 : 9)) + 2) / 5 + d - 1;
    long long doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    return era * 146097 + doe - 719468;
}

/* wit.device_time_ns: the calendar time of a 0x50 packet, valid=0 for no date */
static int device_time(const unsigned char *p, int64_t *out)
{
    int year = 2000 + p[0], month = p[1], day = p[2], hh = p[3], mm = p[4], ss = p[5];
    static const int mdays[] = {31, 28, 31, 30, 31, 30, 31, 31, 30, 31, 30, 31};
    if (month < 1 || month > 12 || day < 1 || hh > 23 || mm > 59 || ss > 59)
        return 0;
    int leap = (year % 4 == 0 && year % 100 != 0) || year % 400 == 0;
    if (day > mdays[month - 1] + (month == 2 && leap))
        return 0;
    long long s = days_from_civil(year, month, day) * 86400LL + hh * 3600 + mm * 60 + ss;
    *out = (int64_t)(s * 1000000000LL + (long long)(p[6] | (p[7] << 8)) * 1000000LL);
    return 1;
}

static PyObject *vec(const double *v, int n)
{
    PyObject *t = PyTuple_New(n);
    for (int i = 0; t != NULL && i < n; i++) {
        PyObject *x = PyFloat_FromDouble(v[i]);
        if (x == NULL)
            Py_CLEAR(t);
        else
            PyTuple_SET_ITEM(t, i, x);
    }
    return t;
}

/* an ImuSample, its slots set by their descriptors as the dataclass's __init__ sets them */
static PyObject *make_sample(WitStream *s)
{
    Cycle *c = &s->cycle;
    PyObject *values[N_SLOTS] = {
        PyLong_FromLongLong(s->cycle_t_ns), vec(c->acc, 3), vec(c->gyro, 3),
        c->has_temp ? PyFloat_FromDouble(c->temp) : Py_NewRef(Py_None),
        c->has_angle ? vec(c->angle, 3) : Py_NewRef(Py_None),
        c->has_mag ? Py_BuildValue("(lll)", c->mag[0], c->mag[1], c->mag[2])
                   : Py_NewRef(Py_None),
        c->has_quat ? vec(c->quat, 4) : Py_NewRef(Py_None),
        c->has_time && c->time_valid ? PyLong_FromLongLong(c->time_ns) : Py_NewRef(Py_None)};
    return drivers_make(s->sample_type, s->slots, values, N_SLOTS);
}

/* WitParser._close: the cycle out as a sample when it holds accel and gyro */
static int close_cycle(WitStream *s, PyObject *out)
{
    Cycle *c = &s->cycle;
    int rc = 0;
    int any = c->has_acc || c->has_gyro || c->has_temp || c->has_angle || c->has_mag ||
              c->has_quat || c->has_time;
    if (c->has_acc && c->has_gyro) {
        s->closing_type = s->cycle_max;
        PyObject *sample = make_sample(s);
        rc = sample == NULL ? -1 : PyList_Append(out, sample);
        Py_XDECREF(sample);
        s->frames++;
    } else if (any || s->cycle_max >= 0) {
        s->dropped++;
    }
    memset(c, 0, sizeof *c);
    s->last_type = -1;
    s->cycle_max = -1;
    return rc;
}

static void decode(WitStream *s, int ptype, const unsigned char *d)
{
    Cycle *c = &s->cycle;
    int tw = s->temp_word; /* the temperature's byte offset in the payload */
    switch (s->kind[ptype]) {
    case TIME:
        c->has_time = 1;
        c->time_valid = device_time(d, &c->time_ns);
        return;
    case ACC:
    case GYRO:
    case ANGLE:
    case QUAT: {
        int k = s->kind[ptype];
        double div = s->div[k == ACC ? DIV_ACC : k == GYRO ? DIV_GYRO
                            : k == ANGLE ? DIV_ANGLE : DIV_QUAT];
        double *dst = k == ACC ? c->acc : k == GYRO ? c->gyro : k == ANGLE ? c->angle : c->quat;
        for (int i = 0; i < (k == QUAT ? 4 : 3); i++)
            dst[i] = (double)i16(d + 2 * i) / div;
        *(k == ACC ? &c->has_acc : k == GYRO ? &c->has_gyro
          : k == ANGLE ? &c->has_angle : &c->has_quat) = 1;
        if (k == ACC || k == GYRO) {
            c->has_temp = 1;
            c->temp = (double)i16(d + tw) / s->div[DIV_TEMP];
        }
        return;
    }
    case MAG:
        for (int i = 0; i < 3; i++)
            c->mag[i] = i16(d + 2 * i);
        c->has_mag = 1;
        c->has_temp = 1;
        c->temp = (double)i16(d + tw) / s->div[DIV_TEMP];
        return;
    default:
        return; /* a known type without a layout: part of the cycle, no fields */
    }
}

/* WitParser._packet */
static int packet(WitStream *s, int ptype, const unsigned char *payload, long long t_ns,
                  PyObject *out)
{
    if (s->kind[ptype] == READBACK)
        return 0;
    if (ptype <= s->last_type) {
        if (s->cycle_max >= 0 && close_cycle(s, out) < 0)
            return -1;
    } else if (s->closing_type >= 0 && s->last_type == s->closing_type && s->cycle_max < 0) {
        s->closing_type = -1; /* the device's cycle grew: relearn */
    }
    s->last_type = ptype;
    if (ptype > s->cycle_max)
        s->cycle_max = ptype;
    s->cycle_t_ns = t_ns;
    decode(s, ptype, payload);
    if (ptype == s->closing_type) {
        if (close_cycle(s, out) < 0)
            return -1;
        s->last_type = ptype;
    }
    return 0;
}

static Py_ssize_t find_header(int header, const unsigned char *b, Py_ssize_t from,
                              Py_ssize_t len)
{
    if (from >= len)
        return -1;
    const unsigned char *p = memchr(b + from, header, (size_t)(len - from));
    return p == NULL ? -1 : p - b;
}

/* scan_fixed's byte-by-byte resync loop, each accepted packet handled at once; the
 * unconsumed tail kept (drivers/base.py: _scan_loop, _finish, note_scan, _keep_tail) */
static int scan(WitStream *s, const unsigned char *b, Py_ssize_t len, long long t_ns,
                PyObject *out)
{
    const int h = s->header, n = s->packet_len;
    Py_ssize_t last = len - n, end = 0, n_starts = 0;
    Py_ssize_t p = find_header(h, b, 0, len);
    while (p >= 0 && p <= last) {
        if (!s->known[b[p + 1]]) {
            s->unknown_types++;
        } else {
            unsigned sum = 0;
            for (int i = 0; i < n - 1; i++)
                sum += b[p + i];
            if ((sum & 0xFF) == b[p + n - 1]) {
                if (packet(s, b[p + 1], b + p + 2, t_ns, out) < 0)
                    return -1;
                n_starts++;
                end = p + n;
                p = find_header(h, b, end, len);
                continue;
            }
            s->checksum_errors++;
            note_error(s, s->base + p);
        }
        p = find_header(h, b, p + 1, len);
    }
    Py_ssize_t from = end > len - n + 1 ? end : len - n + 1;
    Py_ssize_t tail = find_header(h, b, from > 0 ? from : 0, len);
    Py_ssize_t keep = tail >= 0 ? tail : len;
    s->bytes_skipped += keep - n_starts * n;
    s->base += keep;
    Py_ssize_t rest = len - keep;
    if (rest > s->cap) {
        unsigned char *grown = PyMem_Realloc(s->buf, (size_t)rest);
        if (grown == NULL) {
            PyErr_NoMemory();
            return -1;
        }
        s->buf = grown;
        s->cap = rest;
    }
    memmove(s->buf, b + keep, (size_t)rest);
    s->len = rest;
    return 0;
}

static PyObject *feed(WitStream *s, PyObject *const *args, Py_ssize_t nargs)
{
    long long t_ns = 0;
    if (nargs < 1 || nargs > 2 || (nargs == 2 && (t_ns = PyLong_AsLongLong(args[1])) == -1 &&
                                   PyErr_Occurred())) {
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_TypeError, "feed(data, t_ns=0)");
        return NULL;
    }
    Py_buffer view;
    if (PyObject_GetBuffer(args[0], &view, PyBUF_SIMPLE) < 0)
        return NULL;
    PyObject *out = PyList_New(0);
    s->bytes_in += view.len;
    unsigned char *joined = NULL;
    const unsigned char *b = view.buf;
    Py_ssize_t len = view.len;
    if (s->len > 0) { /* the held tail and this read, as one buffer */
        joined = PyMem_Malloc((size_t)(s->len + view.len) + 1);
        if (joined == NULL) {
            PyErr_NoMemory();
            Py_CLEAR(out);
        } else {
            memcpy(joined, s->buf, (size_t)s->len);
            memcpy(joined + s->len, view.buf, (size_t)view.len);
            b = joined;
            len = s->len + view.len;
        }
    }
    if (out != NULL && scan(s, b, len, t_ns, out) < 0)
        Py_CLEAR(out);
    PyMem_Free(joined);
    PyBuffer_Release(&view);
    return out;
}

static PyObject *flush(WitStream *s, PyObject *unused)
{
    (void)unused;
    PyObject *out = PyList_New(0);
    if (out != NULL && close_cycle(s, out) < 0)
        Py_CLEAR(out);
    s->bytes_skipped += s->len;
    s->base += s->len;
    s->len = 0;
    return out;
}

static PyObject *errors(WitStream *s, PyObject *unused)
{
    (void)unused;
    PyObject *out = PyList_New(s->n_errors);
    int first = (s->error_head - s->n_errors + MAX_ERRORS) % MAX_ERRORS;
    for (int i = 0; out != NULL && i < s->n_errors; i++) {
        PyObject *x = PyLong_FromLongLong(s->errors[(first + i) % MAX_ERRORS]);
        if (x == NULL)
            Py_CLEAR(out);
        else
            PyList_SET_ITEM(out, i, x);
    }
    if (out != NULL)
        s->n_errors = 0;
    return out;
}

static PyObject *get_counts(WitStream *s, void *closure)
{
    (void)closure;
    return Py_BuildValue("(LLLLLL)", s->frames, s->bytes_in, s->bytes_skipped,
                         s->checksum_errors, s->unknown_types, s->dropped);
}

static PyObject *get_pending(WitStream *s, void *closure)
{
    (void)closure;
    return PyBytes_FromStringAndSize((const char *)s->buf, s->len);
}

/* init's layout: (header, packet length, temperature offset, the types of time, acc, gyro,
 * angle, mag, quaternion and read-back, and every known type as a tuple) */
static int read_layout(WitStream *s, PyObject *layout)
{
    enum { SCALARS = 3, TYPES = N_KINDS - 1 };
    if (!PyTuple_Check(layout) || PyTuple_GET_SIZE(layout) != SCALARS + TYPES + 1 ||
        !PyTuple_Check(PyTuple_GET_ITEM(layout, SCALARS + TYPES))) {
        PyErr_SetString(PyExc_TypeError, "WitStream: layout (header, packet length, "
                        "temperature offset, 7 packet types, the known types) expected");
        return -1;
    }
    long v[SCALARS + TYPES];
    for (int i = 0; i < SCALARS + TYPES; i++)
        if ((v[i] = PyLong_AsLong(PyTuple_GET_ITEM(layout, i))) == -1 && PyErr_Occurred())
            return -1;
    for (int k = 0; k < TYPES; k++)
        if (v[SCALARS + k] < 0 || v[SCALARS + k] > 255) {
            PyErr_SetString(PyExc_ValueError, "WitStream: a packet type is a byte");
            return -1;
        }
    s->header = (int)v[0];
    s->packet_len = (int)v[1];
    s->temp_word = (int)v[2];
    memset(s->kind, K_NONE, sizeof s->kind);
    memset(s->known, 0, sizeof s->known);
    for (int k = 0; k < TYPES; k++)
        s->kind[v[SCALARS + k]] = (unsigned char)(TIME + k);
    PyObject *known = PyTuple_GET_ITEM(layout, SCALARS + TYPES);
    for (Py_ssize_t i = 0; i < PyTuple_GET_SIZE(known); i++) {
        long t = PyLong_AsLong(PyTuple_GET_ITEM(known, i));
        if (t < 0 || t > 255) {
            if (!PyErr_Occurred())
                PyErr_SetString(PyExc_ValueError, "WitStream: a packet type is a byte");
            return -1;
        }
        s->known[t] = 1;
    }
    /* header, type, 8 payload bytes (four words: TIME and QUAT read them all), checksum */
    if (s->header < 0 || s->header > 255 || s->packet_len < 11 || s->temp_word < 0 ||
        s->temp_word + 2 > s->packet_len - 3) {
        PyErr_SetString(PyExc_ValueError, "WitStream: the layout does not fit a packet");
        return -1;
    }
    return 0;
}

static int init(WitStream *s, PyObject *args, PyObject *kwds)
{
    PyObject *type, *slots, *divs, *layout;
    static char *names[] = {"sample_type", "slots", "divisors", "layout", NULL};
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "O!O!O!O", names, &PyType_Type, &type,
                                     &PyTuple_Type, &slots, &PyTuple_Type, &divs, &layout) ||
        read_layout(s, layout) < 0)
        return -1;
    if (PyTuple_GET_SIZE(slots) != N_SLOTS || PyTuple_GET_SIZE(divs) != N_DIVS) {
        PyErr_SetString(PyExc_TypeError, "WitStream: 8 slots and 5 divisors expected");
        return -1;
    }
    for (int i = 0; i < N_DIVS; i++) {
        s->div[i] = PyFloat_AsDouble(PyTuple_GET_ITEM(divs, i));
        if (s->div[i] == -1.0 && PyErr_Occurred())
            return -1;
    }
    Py_XSETREF(s->sample_type, Py_NewRef(type));
    Py_XSETREF(s->slots, Py_NewRef(slots));
    memset(&s->cycle, 0, sizeof s->cycle);
    s->last_type = s->cycle_max = s->closing_type = -1;
    return 0;
}

static void dealloc(WitStream *s)
{
    Py_XDECREF(s->sample_type);
    Py_XDECREF(s->slots);
    PyMem_Free(s->buf);
    Py_TYPE(s)->tp_free((PyObject *)s);
}

static PyMethodDef methods[] = {
    {"feed", (PyCFunction)(void (*)(void))feed, METH_FASTCALL,
     "The samples completed by one read (its last byte at t_ns)."},
    {"flush", (PyCFunction)flush, METH_NOARGS,
     "End of input: the pending cycle if complete; leftover bytes counted."},
    {"errors", (PyCFunction)errors, METH_NOARGS,
     "Stream offsets of the checksum mismatches since the last call (the last 16)."},
    {NULL, NULL, 0, NULL},
};

static PyGetSetDef getset[] = {
    {"counts", (getter)get_counts, NULL,
     "(frames, bytes_in, bytes_skipped, checksum_errors, unknown_types, dropped)", NULL},
    {"pending", (getter)get_pending, NULL, "The bytes held for the next read.", NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

PyTypeObject WitStreamType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "drivers._frames.WitStream",
    .tp_basicsize = sizeof(WitStream),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "The WitMotion stream parser (drivers/wit.py's WitParser) in C.",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)init,
    .tp_dealloc = (destructor)dealloc,
    .tp_methods = methods,
    .tp_getset = getset,
};
