/* uwbd.fusion._core.imu_step and imu_read: the common IMU sample, and the common IMU read,
 * whole, in one call each.
 *
 * Almost every IMU sample is the same case: in order, passing the integrity check, for a
 * filter that is running (or waiting for its start). In Python it passes through
 * ImuCheck.judge, the body maps, ImuWindow.add and Eskf.predict (Filter._predict);
 * imu_step does what they do, on their own attributes, in their order, with their
 * arithmetic (the same bits). And almost every read of a WitMotion IMU is one accel and one
 * gyro packet, the cycle the parser expects, which the aligner passes straight on: imu_read
 * does WitParser._common_cycle, Pipeline._spread and Aligner.push too, then the same step.
 *
 * Each declines (returns None, having changed nothing) for anything else: another read, a
 * parser mid-cycle, a held or late frame, a sample the check would reject or might, the
 * filter re-levelling or after a gap. Python then takes it as before, so the Python code
 * stays the reference and handles every case; these handle the common one.
 *
 * The objects arrive as their instance dicts (vars(obj)), in the orders of the enums below:
 * Filter.step_parts and uwbd.service.imu_read.imu_read_path make them.
 *   imu_step(step_parts, t_ns, acc, gyro) -> True | body | None
 *   imu_read(read_parts, data, t_ns) -> ImuSample | (ImuSample, body) | None
 * A covariance due is propagated here (uwbd_propagate) where the C core can take the
 * propagation whole; else body (the sample in body axes): integrated, and the covariance is
 * due: the caller propagates (Filter.finish_prediction), as Filter._predict would have next.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "_core.h"

enum {  /* imu_read's parts */
    P_PARSER, P_STATS, P_LAST_FRAME, P_PERIOD, P_SOURCE, P_ALIGNER, P_SAMPLE_TYPE, P_FIELDS,
    P_DIVISORS, P_STEP, P_COUNT
};
enum { D_ACC, D_GYRO, D_TEMP, D_COUNT };  /* parts[P_DIVISORS]: raw -> SI, floats */
enum {  /* the filter step's parts (imu_step's first argument, parts[P_STEP]) */
    F_FILTER, F_CHECK, F_WINDOW, F_SAMPLES, F_CONSTS, F_WINDOW_NS, F_COUNT
};
enum {  /* step parts[F_CONSTS]: floats */
    C_ACC_M = 0, C_ACC_B = 9, C_GYRO_M = 12, C_GYRO_B = 21, C_GYRO_O = 24, C_BAND = 27,
    C_ACC_CLIP, C_GYRO_CLIP, C_ACC_JUMP, C_GYRO_JUMP, C_JUMP_RUN, C_MAX_GAP, C_PROPAGATE,
    C_COUNT
};
#define SAMPLE_FIELDS 8  /* ImuSample's, in order */
#define WIT_HEADER 0x55
#define WIT_ACC 0x51
#define WIT_GYRO 0x52
#define CYCLE_LEN 22
#define LIMIT_NS (INT64_C(1) << 52)  /* differences below this are exact as doubles */
#define LIMIT_T (INT64_C(1) << 62)   /* times within ±this: no difference overflows */

enum {
    N_BUF, N_CLOSING, N_LAST_TYPE, N_CYCLE_MAX, N_CYCLE, N_BASE, N_CYCLE_T, N_BYTES_IN,
    N_FRAMES, N_WAIT, N_HEAP, N_RELEASED, N_CLOCK, N_IMU_T, N_EKF, N_RELEVEL, N_T, N_FIRST_T,
    N_GOOD_T, N_LAST_IMU, N_LAST_GOOD, N_JUMP_RUN, N_BURST, N_LAST_NS, N_ADDED, N_APPEND,
    N_POPLEFT, N_COUNT
};
static const char *const name_text[N_COUNT] = {
    "_buf", "_closing_type", "_last_type", "_cycle_max", "_cycle", "_base", "_cycle_t_ns",
    "bytes_in", "frames", "wait_ns", "_heap", "_released_ns", "_clock_ns", "_imu_t_ns", "ekf",
    "_relevel", "t_ns", "_first_t_ns", "_good_imu_ns", "_last_imu", "last_good", "_jump_run",
    "_burst_start_ns", "_last_ns", "_added", "append", "popleft",
};
static PyObject *names[N_COUNT];

int uwbd_imu_read_init(void)
{
    return uwbd_intern(name_text, names, N_COUNT);
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

/* An int within ±2^62 (1), None (1 and *none set, if none is given), else 0 (decline);
 * -1 an error. */
int uwbd_as_i64(PyObject *v, int64_t *out, int *none)
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
    return !overflow && x > -LIMIT_T && x < LIMIT_T;
}

/* 1 yes, 0 not so (decline), -1 an error: as_i64 of ns[name] */
static int attr_i64(PyObject *ns, int name, int64_t *out, int *none)
{
    PyObject *v = attr(ns, name);
    return v == NULL ? -1 : uwbd_as_i64(v, out, none);
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

/* ns[name] + k (Python ints), new; NULL with an error set */
static PyObject *plus(PyObject *ns, int name, long k)
{
    PyObject *v = attr(ns, name);
    if (v == NULL)
        return NULL;
    PyObject *step = PyLong_FromLong(k);
    PyObject *sum = step == NULL ? NULL : PyNumber_Add(v, step);
    Py_XDECREF(step);
    return sum;
}

/* A dict's int value for key (*none when absent), as attr_i64. */
static int item_i64(PyObject *dict, PyObject *key, int64_t *out, int *none)
{
    PyObject *v = PyDict_GetItemWithError(dict, key); /* borrowed */
    if (v == NULL) {
        *none = 1;
        return PyErr_Occurred() ? -1 : 1;
    }
    return uwbd_as_i64(v, out, none);
}

/* -- values ------------------------------------------------------------------------------ */

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
        if (!isfinite(acc[i]) || !isfinite(gyro[i]) || fabs(acc[i]) >= c[C_ACC_CLIP] ||
            fabs(gyro[i]) >= c[C_GYRO_CLIP])
            return 0; /* imu_not_finite, imu_saturated */
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
        !uwbd_floats_of(PyTuple_GET_ITEM(last, 0), la, 3, 0) ||
        !uwbd_floats_of(PyTuple_GET_ITEM(last, 1), lg, 3, 0))
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

/* A read taken: what the checks read, and every object the writes store, made before the
 * first write (so that only dict and deque stores, and the INS step's floats, can fail
 * after it). */
typedef struct {
    int64_t t, prev, state_t, period;
    int has_period, first_none, filter_running;
    double acc[3], gyro[3], temp, ab[3], gb[3]; /* raw, and in body axes */
    PyObject *ekf;     /* the filter's Eskf namespace (new), NULL before the start */
    UwbdNominal nom;   /* its nominal state */
} Read;

enum { O_ACC, O_GYRO, O_TEMP, O_SAMPLE, O_BYTES_IN, O_BASE, O_FRAMES, O_PERIOD, O_PAIR,
       O_ZERO, O_BODY, O_ROW, O_ADDED, O_OLDEST, O_COUNT };

static void release(Read *r, PyObject **o)
{
    Py_CLEAR(r->ekf);
    uwbd_nominal_release(&r->nom);
    for (int i = 0; i < O_COUNT; i++)
        Py_CLEAR(o[i]);
}

static int wit_cycle(PyObject *parser, PyObject *data, const double *d, Read *r)
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
        r->acc[i] = (double)le16(b + 2 + 2 * i) / d[D_ACC];
        r->gyro[i] = (double)le16(b + 13 + 2 * i) / d[D_GYRO];
    }
    r->temp = (double)le16(b + 19) / d[D_TEMP];
    return 1;
}

/* The read's checks (parser, spreading, aligner): everything is read and nothing written.
 * 1 take it, 0 decline, -1 error. */
static int read_takes(PyObject *const *parts, PyObject *data, const double *d, Read *r)
{
    int t;
    if ((t = wit_cycle(parts[P_PARSER], data, d, r)) <= 0)
        return t;
    /* Pipeline._spread: the learned period's next value */
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
    return wait == 0 && r->t >= released;
}

/* The filter step's checks (Filter._predict: in order, checked, the filter running or
 * waiting for its start): everything is read and nothing written. 1, 0 or -1 as above. */
static int step_takes(PyObject *const *fp, const double *c, Read *r)
{
    int t, none;
    int64_t previous;
    if ((t = uwbd_as_i64(fp[F_WINDOW_NS], &previous, NULL)) <= 0)
        return t; /* (a window of 2^62 ns or more: Python's) */
    PyObject *filter = fp[F_FILTER];
    if ((t = attr_i64(filter, N_IMU_T, &r->prev, &none)) <= 0 || none)
        return t < 0 ? -1 : 0; /* the first sample: Python's */
    if (r->t <= r->prev || r->t - r->prev >= LIMIT_NS)
        return 0;
    if ((t = check_passes(fp[F_CHECK], c, r->acc, r->gyro)) <= 0)
        return t;
    if ((t = attr_i64(filter, N_FIRST_T, &previous, &r->first_none)) <= 0)
        return t;
    PyObject *ekf = attr(filter, N_EKF);
    if (ekf == NULL)
        return -1;
    r->filter_running = ekf != Py_None;
    if (!r->filter_running)
        return 1;
    if ((t = attr_none(filter, N_RELEVEL)) <= 0)
        return t;
    if ((double)(r->t - r->prev) / 1e9 > c[C_MAX_GAP])
        return 0; /* a gap: coasted in Python */
    if ((t = attr_i64(filter, N_T, &r->state_t, &none)) <= 0 || none)
        return t < 0 ? -1 : 0;
    int64_t ahead = r->t - r->state_t;
    if (ahead >= LIMIT_NS || ahead <= -LIMIT_NS)
        return 0;
    if ((r->ekf = PyObject_GenericGetDict(ekf, NULL)) == NULL)
        return -1;
    return uwbd_nominal_read(r->ekf, &r->nom);
}

/* Every object the read's own writes store, made now: 0, or -1 with an error set. */
static int read_objects(PyObject *const *parts, PyObject *t_obj, Read *r, PyObject **o)
{
    if ((o[O_ACC] = uwbd_floats(r->acc, 3, 0)) == NULL ||
        (o[O_GYRO] = uwbd_floats(r->gyro, 3, 0)) == NULL ||
        (o[O_TEMP] = PyFloat_FromDouble(r->temp)) == NULL)
        return -1;
    PyObject *values[SAMPLE_FIELDS] = {t_obj, o[O_ACC], o[O_GYRO], o[O_TEMP], Py_None,
                                       Py_None, Py_None, Py_None};
    if ((o[O_SAMPLE] = new_sample(parts[P_SAMPLE_TYPE], parts[P_FIELDS], values)) == NULL ||
        (o[O_BYTES_IN] = plus(parts[P_STATS], N_BYTES_IN, CYCLE_LEN)) == NULL ||
        (o[O_BASE] = plus(parts[P_PARSER], N_BASE, CYCLE_LEN)) == NULL ||
        (o[O_FRAMES] = plus(parts[P_STATS], N_FRAMES, 1)) == NULL ||
        (r->has_period && (o[O_PERIOD] = PyLong_FromLongLong(r->period)) == NULL))
        return -1;
    return 0;
}

/* Every object the filter step's writes store, made now (acc and gyro: the sample's own
 * tuples, which the check keeps as the last good pair): 0, or -1 with an error set. */
static int step_objects(PyObject *const *fp, PyObject *t_obj, const double *c, Read *r,
                        PyObject *acc, PyObject *gyro, PyObject **o)
{
    double *ab = r->ab, *gb = r->gb;
    affine(c + C_ACC_M, c + C_ACC_B, r->acc, ab);
    if (c[C_BAND] > 0.0)
        banded(c + C_GYRO_M, c + C_GYRO_O, c[C_BAND], r->gyro, gb);
    else
        affine(c + C_GYRO_M, c + C_GYRO_B, r->gyro, gb);
    if ((o[O_PAIR] = PyTuple_Pack(2, acc, gyro)) == NULL ||
        (o[O_ZERO] = PyLong_FromLong(0)) == NULL ||
        (o[O_ADDED] = plus(fp[F_WINDOW], N_ADDED, 1)) == NULL ||
        (o[O_OLDEST] = PyNumber_Subtract(t_obj, fp[F_WINDOW_NS])) == NULL)
        return -1;
    PyObject *ab_t = uwbd_floats(ab, 3, 0);
    PyObject *gb_t = ab_t == NULL ? NULL : uwbd_floats(gb, 3, 0);
    o[O_BODY] = gb_t == NULL ? NULL : PyTuple_Pack(2, ab_t, gb_t);
    Py_XDECREF(ab_t);
    Py_XDECREF(gb_t);
    if (o[O_BODY] == NULL || (o[O_ROW] = PyTuple_New(7)) == NULL)
        return -1;
    double v[6] = {ab[0], ab[1], ab[2], gb[0], gb[1], gb[2]};
    Py_INCREF(t_obj);
    PyTuple_SET_ITEM(o[O_ROW], 0, t_obj);
    for (int i = 0; i < 6; i++) {
        PyObject *f = PyFloat_FromDouble(v[i]);
        if (f == NULL)
            return -1;
        PyTuple_SET_ITEM(o[O_ROW], i + 1, f);
    }
    return 0;
}

/* ImuWindow.add: the row in, those older than the window out */
static int window_add(PyObject *const *fp, PyObject *row, PyObject *added, PyObject *oldest)
{
    PyObject *samples = fp[F_SAMPLES];
    PyObject *rc = PyObject_CallMethodOneArg(samples, names[N_APPEND], row);
    if (rc == NULL)
        return -1;
    Py_DECREF(rc);
    if (set_attr(fp[F_WINDOW], N_ADDED, added) < 0)
        return -1;
    for (;;) { /* while samples[0][0] < oldest_ns: popleft() */
        PyObject *first = PySequence_GetItem(samples, 0);
        if (first == NULL)
            return -1;
        if (!PyTuple_Check(first) || PyTuple_GET_SIZE(first) == 0) {
            Py_DECREF(first);
            PyErr_SetString(PyExc_TypeError, "imu_read: a window row is not (t_ns, ...)");
            return -1;
        }
        /* Python's own comparison: a row's time may be any number Python put there */
        int older = PyObject_RichCompareBool(PyTuple_GET_ITEM(first, 0), oldest, Py_LT);
        Py_DECREF(first);
        if (older <= 0)
            return older;
        rc = PyObject_CallMethodNoArgs(samples, names[N_POPLEFT]);
        if (rc == NULL)
            return -1;
        Py_DECREF(rc);
    }
}

/* Eskf.predict on the C core, on the state read: 1 done and the covariance is due, 0 done,
 * -1 an error. */
static int predict(Read *r, const double acc[3], const double gyro[3], double dt,
                   double propagate_every_s)
{
    double interval;
    if (uwbd_nominal_predict(&r->nom, r->ekf, acc, gyro, dt, &interval) < 0)
        return -1;
    return interval >= propagate_every_s;
}

/* the numbers of the step parts' F_CONSTS into c */
static int numbers_of(PyObject *consts, double c[C_COUNT])
{
    /* those of the last parts seen are kept, with a reference to them (so that no other
     * tuple can take their address): one pipeline reads on and on with the same */
    static PyObject *seen = NULL;
    static double kept[C_COUNT];
    if (consts != seen) {
        if (uwbd_doubles_of(consts, kept, C_COUNT) < 0) {
            Py_CLEAR(seen);
            return -1;
        }
        Py_INCREF(consts);
        Py_XSETREF(seen, consts);
    }
    memcpy(c, kept, sizeof kept); /* this call's own copy */
    return 0;
}

/* The step parts and their numbers, checked: 0, or -1 with an error set. */
static int step_parts(PyObject *obj, PyObject *const **fp, double c[C_COUNT])
{
    if (!PyTuple_Check(obj) || PyTuple_GET_SIZE(obj) != F_COUNT ||
        !PyTuple_Check(PyTuple_GET_ITEM(obj, F_CONSTS)) ||
        PyTuple_GET_SIZE(PyTuple_GET_ITEM(obj, F_CONSTS)) != C_COUNT) {
        PyErr_SetString(PyExc_TypeError, "the step's parts are not as Filter makes them");
        return -1;
    }
    *fp = &PyTuple_GET_ITEM(obj, 0);
    return numbers_of(PyTuple_GET_ITEM(obj, F_CONSTS), c);
}

/* Filter._predict's writes, in its order, once everything is made: 1 done and the
 * covariance is due (Filter.finish_prediction goes on), 0 done, -1 an error. */
static int step_writes(PyObject *const *fp, PyObject *t_obj, const double *c, Read *r,
                       PyObject **o)
{
    PyObject *filter = fp[F_FILTER], *check = fp[F_CHECK];
    if (/* ImuCheck.judge */
        set_attr(check, N_JUMP_RUN, o[O_ZERO]) < 0 || set_attr(check, N_LAST_GOOD, o[O_PAIR]) < 0 ||
        set_attr(check, N_BURST, Py_None) < 0 || set_attr(check, N_LAST_NS, t_obj) < 0 ||
        (r->first_none && set_attr(filter, N_FIRST_T, t_obj) < 0) ||
        set_attr(filter, N_IMU_T, t_obj) < 0 ||
        window_add(fp, o[O_ROW], o[O_ADDED], o[O_OLDEST]) < 0 ||
        set_attr(filter, N_GOOD_T, t_obj) < 0)
        return -1;
    if (r->filter_running) {
        double dt = (double)(r->t - r->state_t) / 1e9;
        if (dt > 0) {
            int due = predict(r, r->ab, r->gb, dt, c[C_PROPAGATE]);
            if (due > 0) { /* Filter.finish_prediction: the propagation, here where it can */
                int done = uwbd_propagate(r->ekf);
                due = done < 0 ? -1 : done == 0; /* (not done: the caller's) */
            }
            if (due != 0)
                return due; /* (due: t_ns and _last_imu are set after the propagation) */
        }
        if (set_attr(filter, N_T, t_obj) < 0)
            return -1;
    }
    return set_attr(filter, N_LAST_IMU, o[O_BODY]) < 0 ? -1 : 0;
}

/* imu_step(step_parts, t_ns, acc, gyro) -> True | body | None: Filter.predict's common
 * sample (checked, in order, the filter running or waiting for its start); body: done, and
 * the covariance is due (Filter.finish_prediction); None: nothing changed, Python's. */
PyObject *uwbd_imu_step(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    PyObject *const *fp;
    double c[C_COUNT];
    if (nargs != 4) {
        PyErr_SetString(PyExc_TypeError, "imu_step(parts, t_ns, acc, gyro)");
        return NULL;
    }
    if (step_parts(args[0], &fp, c) < 0)
        return NULL;
    Read r = {0};
    PyObject *o[O_COUNT] = {NULL}, *t_obj = args[1], *acc = args[2], *gyro = args[3];
    int t = uwbd_as_i64(t_obj, &r.t, NULL);
    if (t == 1 && !(PyTuple_CheckExact(acc) && uwbd_floats_of(acc, r.acc, 3, 0) &&
                    PyTuple_CheckExact(gyro) && uwbd_floats_of(gyro, r.gyro, 3, 0)))
        t = 0; /* (a sample not of plain floats: Python's) */
    if (t == 1)
        t = step_takes(fp, c, &r);
    if (t == 1)
        t = step_objects(fp, t_obj, c, &r, acc, gyro, o) < 0 ? -1 : 1;
    PyObject *out = NULL;
    if (t == 1) {
        int due = step_writes(fp, t_obj, c, &r, o);
        out = due < 0 ? NULL : due ? Py_NewRef(o[O_BODY]) : Py_NewRef(Py_True);
    } else if (t == 0) {
        out = Py_NewRef(Py_None);
    }
    release(&r, o);
    return out;
}

PyObject *uwbd_imu_read(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 3 || !PyTuple_Check(args[0]) || PyTuple_GET_SIZE(args[0]) != P_COUNT) {
        PyErr_SetString(PyExc_TypeError, "imu_read(parts, data, t_ns)");
        return NULL;
    }
    PyObject *const *parts = &PyTuple_GET_ITEM(args[0], 0), *const *fp;
    PyObject *divisors = parts[P_DIVISORS], *t_obj = args[2];
    double c[C_COUNT], d[D_COUNT];
    if (!PyTuple_Check(parts[P_FIELDS]) || PyTuple_GET_SIZE(parts[P_FIELDS]) != SAMPLE_FIELDS ||
        !PyType_Check(parts[P_SAMPLE_TYPE]) || !PyTuple_Check(divisors) ||
        PyTuple_GET_SIZE(divisors) != D_COUNT) {
        PyErr_SetString(PyExc_TypeError, "imu_read: parts not as imu_read_path makes them");
        return NULL;
    }
    if (step_parts(parts[P_STEP], &fp, c) < 0)
        return NULL;
    for (int i = 0; i < D_COUNT; i++)
        if ((d[i] = PyFloat_AsDouble(PyTuple_GET_ITEM(divisors, i))) == -1.0 && PyErr_Occurred())
            return NULL;
    Read r = {0};
    PyObject *o[O_COUNT] = {NULL};
    int t = uwbd_as_i64(t_obj, &r.t, NULL);
    if (t == 1)
        t = read_takes(parts, args[1], d, &r);
    if (t == 1)
        t = step_takes(fp, c, &r);
    if (t == 1)
        t = read_objects(parts, t_obj, &r, o) < 0 ||
            step_objects(fp, t_obj, c, &r, o[O_ACC], o[O_GYRO], o) < 0 ? -1 : 1;
    if (t <= 0) {
        release(&r, o);
        if (t < 0)
            return NULL;
        Py_RETURN_NONE;
    }
    /* Taken: from here on, the writes, in the order the Python code makes them. */
    PyObject *out = NULL, *parser = parts[P_PARSER];
    int due = -1;
    if (/* the parser (WitParser._common_cycle) */
        set_attr(parts[P_STATS], N_BYTES_IN, o[O_BYTES_IN]) >= 0 &&
        set_attr(parser, N_BASE, o[O_BASE]) >= 0 && set_attr(parser, N_CYCLE_T, t_obj) >= 0 &&
        set_attr(parts[P_STATS], N_FRAMES, o[O_FRAMES]) >= 0 &&
        /* Pipeline._spread, Aligner.push */
        (!r.has_period || PyDict_SetItem(parts[P_PERIOD], parts[P_SOURCE], o[O_PERIOD]) >= 0) &&
        PyDict_SetItem(parts[P_LAST_FRAME], parts[P_SOURCE], t_obj) >= 0 &&
        set_attr(parts[P_ALIGNER], N_CLOCK, t_obj) >= 0 &&
        set_attr(parts[P_ALIGNER], N_RELEASED, t_obj) >= 0)
        due = step_writes(fp, t_obj, c, &r, o); /* Filter._predict */
    if (due == 0)
        out = Py_NewRef(o[O_SAMPLE]);
    else if (due > 0) /* Filter.finish_prediction propagates, then sets t_ns and _last_imu */
        out = PyTuple_Pack(2, o[O_SAMPLE], o[O_BODY]);
    release(&r, o);
    return out;
}
