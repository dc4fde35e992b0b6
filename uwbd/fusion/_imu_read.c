/* uwbd.fusion._core.imu_read: the common IMU read whole, in one call.
 *
 * The daemon reads a WitMotion IMU ~200 times a second, and almost every read is the same:
 * one accel packet and one gyro packet, the cycle the parser expects, a sample in order
 * that passes the integrity check, a filter running. In Python that read passes through
 * five objects (WitParser._common_cycle, Pipeline._spread, Aligner.push, ImuCheck.judge,
 * Filter._predict with ImuWindow.add and Eskf.predict); here it is one call that does what
 * they do, on their own attributes, in their order, with their arithmetic (the same bits).
 *
 * It declines (returns None, having changed nothing) for anything else: another read, a
 * parser mid-cycle, a held or late frame, a sample the check would reject or might, the
 * filter starting, re-levelling or after a gap. Python then takes the read as before, so the
 * Python code stays the reference and handles every case; this handles the common one.
 *
 * imu_read(parts, data, t_ns) -> ImuSample | (ImuSample, body) | None
 *   parts: the objects and numbers of uwbd.service.pipeline.imu_read_parts (order below).
 *   (ImuSample, body): the sample was integrated and the covariance is due: the caller
 *   propagates it (Filter.finish_prediction), as Filter._predict would have next.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>

#include "_core.h"

enum {  /* parts */
    P_PARSER, P_STATS, P_LAST_FRAME, P_PERIOD, P_SOURCE, P_ALIGNER, P_FILTER, P_CHECK,
    P_WINDOW, P_SAMPLES, P_SAMPLE_TYPE, P_FIELDS, P_CONSTS, P_WINDOW_NS, P_COUNT
};
enum {  /* parts[P_CONSTS]: floats */
    C_ACC_M = 0, C_ACC_B = 9, C_GYRO_M = 12, C_GYRO_B = 21, C_GYRO_O = 24, C_BAND = 27,
    C_ACC_CLIP, C_GYRO_CLIP, C_ACC_JUMP, C_GYRO_JUMP, C_JUMP_RUN, C_MAX_GAP, C_PROPAGATE,
    C_ACC_DIV, C_GYRO_DIV, C_TEMP_DIV, C_COUNT
};
#define SAMPLE_FIELDS 8  /* ImuSample's, in order */
#define WIT_HEADER 0x55
#define WIT_ACC 0x51
#define WIT_GYRO 0x52
#define CYCLE_LEN 22
#define LIMIT_NS (INT64_C(1) << 52)  /* differences below this are exact as doubles */

enum {
    N_BUF, N_CLOSING, N_LAST_TYPE, N_CYCLE_MAX, N_CYCLE, N_BASE, N_CYCLE_T, N_BYTES_IN,
    N_FRAMES, N_WAIT, N_HEAP, N_RELEASED, N_CLOCK, N_IMU_T, N_EKF, N_RELEVEL, N_T, N_FIRST_T,
    N_GOOD_T, N_LAST_IMU, N_LAST_GOOD, N_JUMP_RUN, N_BURST, N_LAST_NS, N_ADDED, N_P, N_V, N_Q,
    N_BG, N_BA, N_SUM_FN, N_SUM_W, N_INTERVAL, N_GRAVITY, N_APPEND, N_POPLEFT, N_COUNT
};
static const char *const name_text[N_COUNT] = {
    "_buf", "_closing_type", "_last_type", "_cycle_max", "_cycle", "_base", "_cycle_t_ns",
    "bytes_in", "frames", "wait_ns", "_heap", "_released_ns", "_clock_ns", "_imu_t_ns",
    "ekf", "_relevel", "t_ns", "_first_t_ns", "_good_imu_ns", "_last_imu", "last_good",
    "_jump_run", "_burst_start_ns", "_last_ns", "_added", "p", "v", "q", "b_g", "b_a",
    "_sum_fn", "_sum_w", "_T", "gravity_mps2", "append", "popleft",
};
static PyObject *names[N_COUNT];

int uwbd_imu_read_init(void)
{
    for (int i = 0; i < N_COUNT; i++)
        if ((names[i] = PyUnicode_InternFromString(name_text[i])) == NULL)
            return -1;
    return 0;
}

/* -- attributes -------------------------------------------------------------------------
 * The objects arrive as their instance dicts (vars(obj): the live namespace of each, the
 * same for Python's attribute access and this): a dict lookup is a quarter of the cost of
 * PyObject_GetAttr and PyObject_SetAttr. Every name read here is a plain instance attribute
 * set in its class's __init__; a missing one is a bug, said as an AttributeError. */

/* Borrowed: ns[name], or NULL with AttributeError set. */
static PyObject *attr(PyObject *ns, int name)
{
    PyObject *v = PyDict_GetItemWithError(ns, names[name]);
    if (v == NULL && !PyErr_Occurred())
        PyErr_Format(PyExc_AttributeError, "imu_read: no attribute %s", name_text[name]);
    return v;
}

/* An int fitting int64 (1), None (1 and *none set, if none is given), else 0 (decline). */
static int as_i64(PyObject *v, int64_t *out, int *none)
{
    if (none != NULL)
        *none = v == Py_None;
    if (none != NULL && v == Py_None)
        return 1;
    if (!PyLong_CheckExact(v))
        return 0;
    int overflow = 0;
    long long x = PyLong_AsLongLongAndOverflow(v, &overflow);
    if (x == -1 && PyErr_Occurred())
        return -1;
    *out = (int64_t)x;
    return !overflow;
}

/* 1 yes, 0 not so (decline), -1 an error: as_i64 of ns[name] */
static int attr_i64(PyObject *ns, int name, int64_t *out, int *none)
{
    PyObject *v = attr(ns, name);
    return v == NULL ? -1 : as_i64(v, out, none);
}

/* ns[name]'s truth value: 1 true, 0 false, -1 an error. */
static int attr_true(PyObject *ns, int name)
{
    PyObject *v = attr(ns, name);
    return v == NULL ? -1 : PyObject_IsTrue(v);
}

/* ns[name] is None: 1 it is, 0 not, -1 an error. */
static int attr_none(PyObject *ns, int name)
{
    PyObject *v = attr(ns, name);
    return v == NULL ? -1 : v == Py_None;
}

static int set_attr(PyObject *ns, int name, PyObject *value)
{
    return PyDict_SetItem(ns, names[name], value);
}

/* ns[name] += k (Python ints) */
static int add_attr(PyObject *ns, int name, long k)
{
    PyObject *v = attr(ns, name);
    if (v == NULL)
        return -1;
    PyObject *step = PyLong_FromLong(k);
    PyObject *sum = step == NULL ? NULL : PyNumber_Add(v, step);
    Py_XDECREF(step);
    if (sum == NULL)
        return -1;
    int rc = set_attr(ns, name, sum);
    Py_DECREF(sum);
    return rc;
}

/* A float attribute, -1 with an error set if none. */
static int attr_double(PyObject *ns, int name, double *out)
{
    PyObject *v = attr(ns, name);
    if (v == NULL)
        return -1;
    *out = PyFloat_AsDouble(v);
    return *out == -1.0 && PyErr_Occurred() ? -1 : 0;
}

/* A dict's int value for key (*none when absent), as attr_i64. */
static int item_i64(PyObject *dict, PyObject *key, int64_t *out, int *none)
{
    PyObject *v = PyDict_GetItemWithError(dict, key); /* borrowed */
    if (v == NULL) {
        *none = 1;
        return PyErr_Occurred() ? -1 : 1;
    }
    return as_i64(v, out, none);
}

/* -- values ------------------------------------------------------------------------------ */

/* A tuple of n floats (new). */
static PyObject *float_tuple(const double *v, Py_ssize_t n)
{
    PyObject *t = PyTuple_New(n);
    if (t == NULL)
        return NULL;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *f = PyFloat_FromDouble(v[i]);
        if (f == NULL) {
            Py_DECREF(t);
            return NULL;
        }
        PyTuple_SET_ITEM(t, i, f);
    }
    return t;
}

/* n floats out of a list or tuple of exactly n floats (the state's vectors): 1, else 0. */
static int floats_of(PyObject *seq, double *out, Py_ssize_t n)
{
    PyObject **items;
    if (PyList_CheckExact(seq) && PyList_GET_SIZE(seq) == n)
        items = ((PyListObject *)seq)->ob_item;
    else if (PyTuple_CheckExact(seq) && PyTuple_GET_SIZE(seq) == n)
        items = ((PyTupleObject *)seq)->ob_item;
    else
        return 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        if (!PyFloat_CheckExact(items[i]))
            return 0;
        out[i] = PyFloat_AS_DOUBLE(items[i]);
    }
    return 1;
}

/* M v - b, as intrinsics._affine */
static void affine(const double *M, const double *b, const double v[3], double out[3])
{
    for (int i = 0; i < 3; i++)
        out[i] = M[3 * i] * v[0] + M[3 * i + 1] * v[1] + M[3 * i + 2] * v[2] - b[i];
}

/* the gyro with a dead-band, as intrinsics.to_body's gyro() */
static void banded(const double *M, const double *o, double d, const double w[3],
                   double out[3])
{
    double x[3];
    for (int i = 0; i < 3; i++) {
        x[i] = w[i] - o[i];
        if (-d < x[i] && x[i] < d)
            x[i] = 0.0;
    }
    for (int i = 0; i < 3; i++)
        out[i] = M[3 * i] * x[0] + M[3 * i + 1] * x[1] + M[3 * i + 2] * x[2];
}

/* Whether ImuCheck._reason finds nothing against the sample, as far as it can be sure:
 * 1 no reason, 0 a reason or too close to call (decline), -1 an error. */
static int check_passes(PyObject *check, const double *c, const double acc[3],
                        const double gyro[3])
{
    for (int i = 0; i < 3; i++)
        if (fabs(acc[i]) >= c[C_ACC_CLIP] || fabs(gyro[i]) >= c[C_GYRO_CLIP])
            return 0; /* imu_saturated (the values come from int16s: always finite) */
    PyObject *last = attr(check, N_LAST_GOOD);
    if (last == NULL)
        return -1;
    if (last == Py_None)
        return 1;
    int64_t run;
    int got = attr_i64(check, N_JUMP_RUN, &run, NULL);
    if (got <= 0 || (double)run >= c[C_JUMP_RUN])
        return got; /* no jump test after a run of them */
    double la[3], lg[3];
    if (!PyTuple_CheckExact(last) || PyTuple_GET_SIZE(last) != 2 ||
        !floats_of(PyTuple_GET_ITEM(last, 0), la, 3) ||
        !floats_of(PyTuple_GET_ITEM(last, 1), lg, 3))
        return 0;
    double da = 0.0, dg = 0.0;
    for (int i = 0; i < 3; i++) {
        da += (acc[i] - la[i]) * (acc[i] - la[i]);
        dg += (gyro[i] - lg[i]) * (gyro[i] - lg[i]);
    }
    /* math.dist rounds otherwise than this sum: only a clear pass is taken here */
    double margin = 1.0 - 1e-9;
    return da < c[C_ACC_JUMP] * c[C_ACC_JUMP] * margin &&
           dg < c[C_GYRO_JUMP] * c[C_GYRO_JUMP] * margin;
}

/* The sample, as ImuSample(t_ns, acc, gyro, temperature) makes it: its slots set by their
 * descriptors, as the dataclass's own __init__ sets them (object.__setattr__). */
static PyObject *new_sample(PyObject *type, PyObject *fields, PyObject *values[SAMPLE_FIELDS])
{
    PyTypeObject *tp = (PyTypeObject *)type;
    PyObject *obj = tp->tp_alloc(tp, 0);
    if (obj == NULL)
        return NULL;
    for (int i = 0; i < SAMPLE_FIELDS; i++) {
        PyObject *descr = PyTuple_GET_ITEM(fields, i);
        descrsetfunc set = Py_TYPE(descr)->tp_descr_set;
        if (set == NULL || set(descr, obj, values[i]) < 0) {
            if (!PyErr_Occurred())
                PyErr_SetString(PyExc_TypeError, "imu_read: a field of ImuSample is no slot");
            Py_DECREF(obj);
            return NULL;
        }
    }
    return obj;
}

static int16_t le16(const unsigned char *b) { return (int16_t)(b[0] | (b[1] << 8)); }

/* The checks: everything is read and nothing written. 1 take it, 0 decline, -1 error. */
typedef struct {
    int64_t t, prev, state_t, period;
    int state_t_none, has_period, first_none, filter_running;
    double acc[3], gyro[3], temp;
} Read;

static int wit_cycle(PyObject *parser, PyObject *data, const double *c, Read *r)
{
    if (!PyBytes_CheckExact(data) || PyBytes_GET_SIZE(data) != CYCLE_LEN)
        return 0;
    const unsigned char *b = (const unsigned char *)PyBytes_AS_STRING(data);
    if (b[0] != WIT_HEADER || b[1] != WIT_ACC || b[11] != WIT_HEADER || b[12] != WIT_GYRO)
        return 0;
    unsigned s0 = 0, s1 = 0;
    for (int i = 0; i < 10; i++) {
        s0 += b[i];
        s1 += b[11 + i];
    }
    if ((s0 & 0xFF) != b[10] || (s1 & 0xFF) != b[21])
        return 0;
    /* WitParser.feed's fast branch: nothing pending, the closing type learned is gyro */
    int64_t closing, last_type, cycle_max;
    int t;
    if ((t = attr_true(parser, N_BUF)) != 0 || (t = attr_true(parser, N_CYCLE)) != 0)
        return t < 0 ? -1 : 0;
    if ((t = attr_i64(parser, N_CLOSING, &closing, NULL)) <= 0 ||
        (t = attr_i64(parser, N_LAST_TYPE, &last_type, NULL)) <= 0 ||
        (t = attr_i64(parser, N_CYCLE_MAX, &cycle_max, NULL)) <= 0)
        return t;
    if (closing != WIT_GYRO || last_type != WIT_GYRO || cycle_max >= 0)
        return 0;
    for (int i = 0; i < 3; i++) {
        r->acc[i] = (double)le16(b + 2 + 2 * i) / c[C_ACC_DIV];
        r->gyro[i] = (double)le16(b + 13 + 2 * i) / c[C_GYRO_DIV];
    }
    r->temp = (double)le16(b + 19) / c[C_TEMP_DIV];
    return 1;
}

static int takes(PyObject *const *parts, PyObject *data, const double *c, Read *r,
                 PyObject **ekf)
{
    int t, none;
    if ((t = wit_cycle(parts[P_PARSER], data, c, r)) <= 0)
        return t;
    /* Pipeline._spread: the learned period's next value fits in int64 */
    int64_t previous;
    int prev_none, period_none;
    if ((t = item_i64(parts[P_LAST_FRAME], parts[P_SOURCE], &previous, &prev_none)) <= 0 ||
        (t = item_i64(parts[P_PERIOD], parts[P_SOURCE], &r->period, &period_none)) <= 0)
        return t;
    r->has_period = !prev_none && r->t > previous;
    if (r->has_period) {
        int64_t delta = r->t - previous;
        if (delta >= LIMIT_NS || (!period_none && (r->period < 0 || r->period >= LIMIT_NS)))
            return 0;
        r->period = period_none ? delta : (7 * r->period + delta) / 8; /* both >= 0: // */
    }
    /* Aligner.push's pass-through */
    PyObject *aligner = parts[P_ALIGNER];
    int64_t wait, released;
    if ((t = attr_i64(aligner, N_WAIT, &wait, NULL)) <= 0 ||
        (t = attr_i64(aligner, N_RELEASED, &released, NULL)) <= 0)
        return t;
    if ((t = attr_true(aligner, N_HEAP)) != 0)
        return t < 0 ? -1 : 0;
    if (wait != 0 || r->t < released)
        return 0;
    /* Filter._predict: in order, checked, the filter running or waiting for its start */
    PyObject *filter = parts[P_FILTER];
    if ((t = attr_i64(filter, N_IMU_T, &r->prev, &none)) <= 0 || none)
        return t < 0 ? -1 : 0; /* the first sample: Python's */
    if (r->t <= r->prev || r->t - r->prev >= LIMIT_NS)
        return 0;
    if ((t = check_passes(parts[P_CHECK], c, r->acc, r->gyro)) <= 0)
        return t;
    if ((t = attr_i64(filter, N_FIRST_T, &previous, &r->first_none)) <= 0)
        return t;
    *ekf = attr(filter, N_EKF);
    if (*ekf == NULL)
        return -1;
    Py_INCREF(*ekf);
    r->filter_running = *ekf != Py_None;
    if (!r->filter_running)
        return 1;
    if ((t = attr_none(filter, N_RELEVEL)) <= 0)
        return t;
    if ((double)(r->t - r->prev) / 1e9 > c[C_MAX_GAP])
        return 0; /* a gap: coasted in Python */
    if ((t = attr_i64(filter, N_T, &r->state_t, &r->state_t_none)) <= 0 || r->state_t_none)
        return t < 0 ? -1 : 0;
    int64_t ahead = r->t - r->state_t;
    return ahead < LIMIT_NS && ahead > -LIMIT_NS;
}

/* ImuWindow.add */
static int window_add(PyObject *const *parts, PyObject *t_obj, int64_t t, const double ab[3],
                      const double gb[3])
{
    double v[6] = {ab[0], ab[1], ab[2], gb[0], gb[1], gb[2]};
    PyObject *row = PyTuple_New(7);
    if (row == NULL)
        return -1;
    Py_INCREF(t_obj);
    PyTuple_SET_ITEM(row, 0, t_obj);
    for (int i = 0; i < 6; i++) {
        PyObject *f = PyFloat_FromDouble(v[i]);
        if (f == NULL) {
            Py_DECREF(row);
            return -1;
        }
        PyTuple_SET_ITEM(row, i + 1, f);
    }
    PyObject *samples = parts[P_SAMPLES];
    PyObject *rc = PyObject_CallMethodOneArg(samples, names[N_APPEND], row);
    Py_DECREF(row);
    if (rc == NULL)
        return -1;
    Py_DECREF(rc);
    if (add_attr(parts[P_WINDOW], N_ADDED, 1) < 0)
        return -1;
    int64_t length_ns = PyLong_AsLongLong(parts[P_WINDOW_NS]);
    if (length_ns == -1 && PyErr_Occurred())
        return -1;
    int64_t oldest = t - length_ns;
    for (;;) {
        PyObject *first = PySequence_GetItem(samples, 0);
        if (first == NULL)
            return -1;
        PyObject *t0 = PyTuple_Check(first) ? PyTuple_GET_ITEM(first, 0) : NULL;
        long long first_ns = t0 == NULL ? 0 : PyLong_AsLongLong(t0);
        Py_DECREF(first);
        if (t0 == NULL || (first_ns == -1 && PyErr_Occurred())) {
            if (!PyErr_Occurred())
                PyErr_SetString(PyExc_TypeError, "imu_read: a window row is no tuple");
            return -1;
        }
        if (first_ns >= oldest)
            return 0;
        rc = PyObject_CallMethodNoArgs(samples, names[N_POPLEFT]);
        if (rc == NULL)
            return -1;
        Py_DECREF(rc);
    }
}

/* Eskf.predict on the C core: 1 done and the covariance is due, 0 done, -1 an error. */
static int predict(PyObject *ekf, const double acc[3], const double gyro[3], double dt,
                   double propagate_every_s)
{
    double st[7][4], g, interval;
    const int sizes[7] = {3, 3, 4, 3, 3, 3, 3};
    const int which[7] = {N_P, N_V, N_Q, N_BG, N_BA, N_SUM_FN, N_SUM_W};
    PyObject *lists[7];
    PyObject *ns = PyObject_GenericGetDict(ekf, NULL);
    if (ns == NULL)
        return -1;
    int rc = -1;
    for (int i = 0; i < 7; i++) {
        lists[i] = attr(ns, which[i]);
        if (lists[i] == NULL)
            goto done;
        if (!floats_of(lists[i], st[i], sizes[i]) &&
            uwbd_get_vec(lists[i], st[i], sizes[i], name_text[which[i]]))
            goto done;
    }
    if (attr_double(ns, N_GRAVITY, &g) < 0 || attr_double(ns, N_INTERVAL, &interval) < 0)
        goto done;
    double qn[4];
    uwbd_predict_step(st[0], st[1], st[2], st[3], st[4], st[5], st[6], acc, gyro, dt, g, qn);
    if (uwbd_set_list(lists[0], st[0], 3) || uwbd_set_list(lists[1], st[1], 3) ||
        uwbd_set_list(lists[5], st[5], 3) || uwbd_set_list(lists[6], st[6], 3))
        goto done;
    PyObject *q = PyList_New(4);
    if (q == NULL)
        goto done;
    for (int i = 0; i < 4; i++) {
        PyObject *f = PyFloat_FromDouble(qn[i]);
        if (f == NULL) {
            Py_DECREF(q);
            goto done;
        }
        PyList_SET_ITEM(q, i, f);
    }
    int failed = set_attr(ns, N_Q, q) < 0;
    Py_DECREF(q);
    if (failed)
        goto done;
    interval += dt;
    PyObject *T = PyFloat_FromDouble(interval);
    if (T == NULL || set_attr(ns, N_INTERVAL, T) < 0) {
        Py_XDECREF(T);
        goto done;
    }
    Py_DECREF(T);
    rc = interval >= propagate_every_s;
done:
    Py_DECREF(ns);
    return rc;
}

PyObject *uwbd_imu_read(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 3 || !PyTuple_Check(args[0]) || PyTuple_GET_SIZE(args[0]) != P_COUNT) {
        PyErr_SetString(PyExc_TypeError, "imu_read(parts, data, t_ns)");
        return NULL;
    }
    PyObject *const *parts = &PyTuple_GET_ITEM(args[0], 0);
    PyObject *consts = parts[P_CONSTS], *t_obj = args[2];
    if (!PyTuple_Check(consts) || PyTuple_GET_SIZE(consts) != C_COUNT ||
        !PyTuple_Check(parts[P_FIELDS]) || PyTuple_GET_SIZE(parts[P_FIELDS]) != SAMPLE_FIELDS) {
        PyErr_SetString(PyExc_TypeError, "imu_read: parts not as imu_read_parts makes them");
        return NULL;
    }
    /* the numbers of the last parts seen, kept with a reference to them (so that no other
     * tuple can take their address): one pipeline reads on and on with the same */
    static PyObject *seen = NULL;
    static double numbers[C_COUNT];
    if (consts != seen) {
        for (int i = 0; i < C_COUNT; i++) {
            numbers[i] = PyFloat_AsDouble(PyTuple_GET_ITEM(consts, i));
            if (numbers[i] == -1.0 && PyErr_Occurred()) {
                Py_CLEAR(seen);
                return NULL;
            }
        }
        Py_INCREF(consts);
        Py_XSETREF(seen, consts);
    }
    const double *c = numbers;
    Read r;
    if (!PyLong_CheckExact(t_obj))
        Py_RETURN_NONE;
    int overflow = 0;
    r.t = PyLong_AsLongLongAndOverflow(t_obj, &overflow);
    if (r.t == -1 && PyErr_Occurred())
        return NULL;
    if (overflow)
        Py_RETURN_NONE;
    PyObject *ekf = NULL;
    int t = takes(parts, args[1], c, &r, &ekf);
    if (t <= 0) {
        Py_XDECREF(ekf);
        if (t < 0)
            return NULL;
        Py_RETURN_NONE;
    }
    /* Taken: from here on, the writes, in the order the Python code makes them. */
    PyObject *sample = NULL, *acc = float_tuple(r.acc, 3), *gyro = float_tuple(r.gyro, 3);
    PyObject *body = NULL;
    PyObject *temp = PyFloat_FromDouble(r.temp), *out = NULL, *tmp = NULL;
    if (acc == NULL || gyro == NULL || temp == NULL)
        goto done;
    PyObject *values[SAMPLE_FIELDS] = {t_obj, acc, gyro, temp, Py_None, Py_None, Py_None,
                                       Py_None};
    PyObject *parser = parts[P_PARSER], *filter = parts[P_FILTER], *check = parts[P_CHECK];
    /* the parser (WitParser._common_cycle) */
    if (add_attr(parts[P_STATS], N_BYTES_IN, CYCLE_LEN) < 0 ||
        add_attr(parser, N_BASE, CYCLE_LEN) < 0 || set_attr(parser, N_CYCLE_T, t_obj) < 0 ||
        add_attr(parts[P_STATS], N_FRAMES, 1) < 0)
        goto done;
    if ((sample = new_sample(parts[P_SAMPLE_TYPE], parts[P_FIELDS], values)) == NULL)
        goto done;
    /* Pipeline._spread, Aligner.push */
    if (r.has_period) {
        if ((tmp = PyLong_FromLongLong(r.period)) == NULL ||
            PyDict_SetItem(parts[P_PERIOD], parts[P_SOURCE], tmp) < 0)
            goto done;
        Py_CLEAR(tmp);
    }
    if (PyDict_SetItem(parts[P_LAST_FRAME], parts[P_SOURCE], t_obj) < 0 ||
        set_attr(parts[P_ALIGNER], N_CLOCK, t_obj) < 0 ||
        set_attr(parts[P_ALIGNER], N_RELEASED, t_obj) < 0)
        goto done;
    /* ImuCheck.judge */
    if ((tmp = PyLong_FromLong(0)) == NULL || set_attr(check, N_JUMP_RUN, tmp) < 0)
        goto done;
    Py_CLEAR(tmp);
    if ((tmp = PyTuple_Pack(2, acc, gyro)) == NULL || set_attr(check, N_LAST_GOOD, tmp) < 0)
        goto done;
    Py_CLEAR(tmp);
    if (set_attr(check, N_BURST, Py_None) < 0 || set_attr(check, N_LAST_NS, t_obj) < 0)
        goto done;
    /* Filter._predict */
    if ((r.first_none && set_attr(filter, N_FIRST_T, t_obj) < 0) ||
        set_attr(filter, N_IMU_T, t_obj) < 0)
        goto done;
    double ab[3], gb[3];
    affine(c + C_ACC_M, c + C_ACC_B, r.acc, ab);
    if (c[C_BAND] > 0.0)
        banded(c + C_GYRO_M, c + C_GYRO_O, c[C_BAND], r.gyro, gb);
    else
        affine(c + C_GYRO_M, c + C_GYRO_B, r.gyro, gb);
    PyObject *ab_t = float_tuple(ab, 3), *gb_t = ab_t == NULL ? NULL : float_tuple(gb, 3);
    body = gb_t == NULL ? NULL : PyTuple_Pack(2, ab_t, gb_t);
    Py_XDECREF(ab_t);
    Py_XDECREF(gb_t);
    if (body == NULL || window_add(parts, t_obj, r.t, ab, gb) < 0 ||
        set_attr(filter, N_GOOD_T, t_obj) < 0)
        goto done;
    if (r.filter_running) {
        double dt = (double)(r.t - r.state_t) / 1e9;
        if (dt > 0) {
            int due = predict(ekf, ab, gb, dt, c[C_PROPAGATE]);
            if (due < 0)
                goto done;
            if (due) { /* Filter.finish_prediction propagates, then sets t_ns and _last_imu */
                out = PyTuple_Pack(2, sample, body);
                goto done;
            }
        }
        if (set_attr(filter, N_T, t_obj) < 0)
            goto done;
    }
    if (set_attr(filter, N_LAST_IMU, body) < 0)
        goto done;
    out = sample;
    Py_INCREF(out);
done:
    Py_XDECREF(ekf);
    Py_XDECREF(acc);
    Py_XDECREF(gyro);
    Py_XDECREF(temp);
    Py_XDECREF(tmp);
    Py_XDECREF(body);
    Py_XDECREF(sample);
    return out;
}
