/* The IMU front: each sample judged raw, mapped to corrected body axes and, in the common
 * case, integrated into a State, in one call (uwbd/fusion/policy/propagation.py decides when).
 *
 * The references are Python: the screen is checks/imu_check.ImuCheck (judge, burst_s,
 * last_good: this type has the same methods and replaces it on the C core), the maps are
 * checks/intrinsics.to_body's (BodyMaps' numbers, the same arithmetic in the same order).
 * Which sample is the common one (after the last and the state, no gap) is decided here
 * alone: ImuPropagation.predict_many hands every sample while tracking to step_many.
 *
 *   ImuFront(limits, maps, reasons)
 *     limits:  the screen's, in layout.IMU_LIMITS' order (LIMIT_* in _layout.h)
 *     maps:    BodyMaps' numbers in layout.IMU_MAPS' order (MAPS_*; matrices row-major)
 *     reasons: the policy's words for not finite, saturated, jump, and a good sample
 *   .judge(t_ns, acc, gyro) -> "" or the reason     .burst_s(t_ns)     .last_good
 *   .step_many(state, samples, last_ns, state_ns, max_gap_s, propagate_every_s)
 *     -> (rows, reason): over a read's samples while each is the common one: judged; when
 *     good, mapped, State.predict since the state's time and State.propagate when the
 *     interval reaches propagate_every_s; a rejected sample changes nothing but the screen.
 *
 * The jump test's distance is sqrt of the sum of squares where ImuCheck has math.dist (more
 * careful rounding): the two can differ at one rounding exactly at the limit, never else. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>

#include "_core.h"


typedef struct {
    PyObject_HEAD
    double acc_clip, gyro_clip, max_acc_jump, max_gyro_jump;
    long max_jump_run, jump_run;
    double acc_M[9], acc_b[3], gyro_M[9], gyro_b[3], gyro_offset[3], gyro_band;
    double good_acc[3], good_gyro[3];
    int has_good, has_burst, has_last;
    long long burst_start_ns, last_ns;
    PyObject *reasons[4]; /* the policy's words: not finite, saturated, jump; and "" */
} ImuFront;


static double dist3(const double a[3], const double b[3])
{
    double x = a[0] - b[0], y = a[1] - b[1], z = a[2] - b[2];
    return sqrt(x * x + y * y + z * z);
}

/* ImuCheck._reason: -1 when the sample may be used, else the index of its reason */
static int reason_of(ImuFront *s, const double a[3], const double g[3])
{
    if (!isfinite(a[0] + a[1] + a[2] + g[0] + g[1] + g[2]))
        return 0; /* NaN and inf propagate through the sum */
    if (fabs(a[0]) >= s->acc_clip || fabs(a[1]) >= s->acc_clip || fabs(a[2]) >= s->acc_clip ||
        fabs(g[0]) >= s->gyro_clip || fabs(g[1]) >= s->gyro_clip || fabs(g[2]) >= s->gyro_clip)
        return 1;
    if (s->has_good && s->jump_run < s->max_jump_run &&
        (dist3(a, s->good_acc) > s->max_acc_jump || dist3(g, s->good_gyro) > s->max_gyro_jump)) {
        s->jump_run++;
        return 2;
    }
    s->jump_run = 0;
    return -1;
}

/* ImuCheck.judge */
static int judge(ImuFront *s, long long t_ns, const double a[3], const double g[3])
{
    int r = reason_of(s, a, g);
    if (r >= 0) {
        if (!s->has_burst) {
            s->burst_start_ns = s->has_last ? s->last_ns : t_ns;
            s->has_burst = 1;
        }
    } else {
        memcpy(s->good_acc, a, sizeof s->good_acc);
        memcpy(s->good_gyro, g, sizeof s->good_gyro);
        s->has_good = 1;
        s->has_burst = 0;
    }
    s->last_ns = t_ns;
    s->has_last = 1;
    return r;
}

/* M v − b, as intrinsics._affine (to_body's plain rotation is the same with b = 0) */
static void affine(const double M[9], const double b[3], const double v[3], double out[3])
{
    for (int i = 0; i < 3; i++)
        out[i] = M[3 * i] * v[0] + M[3 * i + 1] * v[1] + M[3 * i + 2] * v[2] - b[i];
}

static void to_body(ImuFront *s, const double a[3], const double g[3], double ab[3],
                    double gb[3])
{
    affine(s->acc_M, s->acc_b, a, ab);
    if (s->gyro_band > 0.0) { /* the dead-band is per sensor axis: before the rotation */
        double d = s->gyro_band, w[3];
        for (int i = 0; i < 3; i++) {
            w[i] = g[i] - s->gyro_offset[i];
            if (-d < w[i] && w[i] < d)
                w[i] = 0.0;
        }
        for (int i = 0; i < 3; i++)
            gb[i] = s->gyro_M[3 * i] * w[0] + s->gyro_M[3 * i + 1] * w[1] +
                    s->gyro_M[3 * i + 2] * w[2];
    } else {
        affine(s->gyro_M, s->gyro_b, g, gb);
    }
}

static int sample_args(PyObject *const *args, long long *t_ns, double a[3], double g[3])
{
    *t_ns = PyLong_AsLongLong(args[0]);
    if (*t_ns == -1 && PyErr_Occurred())
        return -1;
    return uwbd_get_vec(args[1], a, 3, "acc") || uwbd_get_vec(args[2], g, 3, "gyro") ? -1 : 0;
}

static PyObject *front_judge(ImuFront *s, PyObject *const *args, Py_ssize_t nargs)
{
    long long t_ns;
    double a[3], g[3];
    if (nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "judge(t_ns, acc, gyro)");
        return NULL;
    }
    if (sample_args(args, &t_ns, a, g) < 0)
        return NULL;
    int r = judge(s, t_ns, a, g);
    return Py_NewRef(s->reasons[r < 0 ? 3 : r]);
}

/* step_many(state, samples, last_ns, state_ns, max_gap_s, propagate_every_s)
 *     -> (rows, reason): over a read's samples, (t_ns, acc, gyro) tuples in time
 * order, while each is the common sample: later than the last (last_ns, then the one
 * before it) by at most max_gap_s and later than the state (state_ns). rows: the samples
 * integrated, (t_ns, acc_b..., gyro_b...) each, as the rest window keeps them; it stops at
 * the first sample that is not the common one (not judged: Python's policy takes it, and
 * reason is None) or that the screen rejects (judged: reason says why, the policy takes it
 * from there). */
static PyObject *front_step_many(ImuFront *s, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 6 || !PyObject_TypeCheck(args[0], &UwbdStateType) || !PyList_Check(args[1])) {
        PyErr_SetString(PyExc_TypeError, "step_many(state, samples: list, last_ns, state_ns, "
                                         "max_gap_s, propagate_every_s): a State first");
        return NULL;
    }
    long long last = PyLong_AsLongLong(args[2]), state_ns = PyLong_AsLongLong(args[3]);
    double max_gap = PyFloat_AsDouble(args[4]), every = PyFloat_AsDouble(args[5]);
    if (PyErr_Occurred())
        return NULL;
    PyObject *rows = PyList_New(0), *reason = Py_None;
    if (rows == NULL)
        return NULL;
    for (Py_ssize_t k = 0; k < PyList_GET_SIZE(args[1]); k++) {
        double ab[3], gb[3];
        int r = uwbd_front_take((PyObject *)s, args[0], PyList_GET_ITEM(args[1], k), &last,
                                &state_ns, max_gap, every, rows, ab, gb);
        if (r == -2)
            goto fail;
        if (r == -1)
            break; /* not the common sample: the policy's */
        if (r > 0) {
            reason = s->reasons[r - 1];
            break;
        }
    }
    return Py_BuildValue("(NO)", rows, reason);
fail:
    Py_DECREF(rows);
    return NULL;
}

int uwbd_front_step(PyObject *front, PyObject *state, long long t_ns, const double a[3],
                    const double g[3], long long *last, long long *state_ns, double max_gap,
                    double every, double ab[3], double gb[3])
{
    ImuFront *s = (ImuFront *)front;
    if (t_ns <= *last || (double)(t_ns - *last) / 1e9 > max_gap || t_ns <= *state_ns)
        return -1;
    int r = judge(s, t_ns, a, g);
    if (r >= 0)
        return 1 + r;
    to_body(s, a, g, ab, gb);
    uwbd_state_predict(state, ab, gb, (double)(t_ns - *state_ns) / 1e9);
    if (uwbd_state_interval(state) >= every)
        uwbd_state_propagate(state);
    *last = *state_ns = t_ns;
    return 0;
}

int uwbd_front_take(PyObject *front, PyObject *state, PyObject *sample, long long *last,
                    long long *state_ns, double max_gap, double every, PyObject *rows,
                    double ab[3], double gb[3])
{
    long long t_ns;
    double a[3], g[3];
    if (!PyTuple_Check(sample) || PyTuple_GET_SIZE(sample) != 3) {
        PyErr_SetString(PyExc_TypeError, "IMU samples are (t_ns, acc, gyro) tuples");
        return -2;
    }
    if (sample_args(&PyTuple_GET_ITEM(sample, 0), &t_ns, a, g) < 0)
        return -2;
    int r = uwbd_front_step(front, state, t_ns, a, g, last, state_ns, max_gap, every, ab, gb);
    if (r != 0)
        return r;
    PyObject *row = Py_BuildValue("(Ldddddd)", t_ns, ab[0], ab[1], ab[2], gb[0], gb[1], gb[2]);
    if (row == NULL || PyList_Append(rows, row) < 0) {
        Py_XDECREF(row);
        return -2;
    }
    Py_DECREF(row);
    return 0;
}

PyObject *uwbd_front_reason(PyObject *front, int r)
{
    return ((ImuFront *)front)->reasons[r - 1];
}

static PyObject *front_burst_s(ImuFront *s, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 1) {
        PyErr_SetString(PyExc_TypeError, "burst_s(t_ns)");
        return NULL;
    }
    long long t_ns = PyLong_AsLongLong(args[0]);
    if (t_ns == -1 && PyErr_Occurred())
        return NULL;
    return PyFloat_FromDouble(s->has_burst ? (double)(t_ns - s->burst_start_ns) / 1e9 : 0.0);
}

static PyObject *get_last_good(ImuFront *s, void *c)
{
    (void)c;
    if (!s->has_good)
        Py_RETURN_NONE;
    PyObject *a = uwbd_floats(s->good_acc, 3, 0), *g = a ? uwbd_floats(s->good_gyro, 3, 0) : NULL;
    PyObject *out = g ? PyTuple_Pack(2, a, g) : NULL;
    Py_XDECREF(a);
    Py_XDECREF(g);
    return out;
}

static int front_init(ImuFront *s, PyObject *args, PyObject *kwds)
{
    static char *names[] = {"limits", "maps", "reasons", NULL};
    double lim[N_LIMITS], maps[N_MAPS];
    PyObject *limits, *map_numbers, *words;
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "OOO!", names, &limits, &map_numbers,
                                     &PyTuple_Type, &words) ||
        uwbd_get_vec(limits, lim, N_LIMITS, "limits") ||
        uwbd_get_vec(map_numbers, maps, N_MAPS, "maps"))
        return -1;
    if (PyTuple_GET_SIZE(words) != 4) {
        PyErr_SetString(PyExc_TypeError, "reasons: (not finite, saturated, jump, good)");
        return -1;
    }
    for (int i = 0; i < 4; i++)
        Py_XSETREF(s->reasons[i], Py_NewRef(PyTuple_GET_ITEM(words, i)));
    s->acc_clip = lim[LIMIT_ACC_CLIP];
    s->gyro_clip = lim[LIMIT_GYRO_CLIP];
    s->max_acc_jump = lim[LIMIT_MAX_ACC_JUMP];
    s->max_gyro_jump = lim[LIMIT_MAX_GYRO_JUMP];
    s->max_jump_run = (long)lim[LIMIT_MAX_JUMP_RUN];
    memcpy(s->acc_M, maps + MAPS_ACC_M, 9 * sizeof(double));
    memcpy(s->acc_b, maps + MAPS_ACC_B, 3 * sizeof(double));
    memcpy(s->gyro_M, maps + MAPS_GYRO_M, 9 * sizeof(double));
    memcpy(s->gyro_b, maps + MAPS_GYRO_B, 3 * sizeof(double));
    memcpy(s->gyro_offset, maps + MAPS_GYRO_OFFSET, 3 * sizeof(double));
    s->gyro_band = maps[MAPS_GYRO_BAND];
    s->jump_run = 0;
    s->has_good = s->has_burst = s->has_last = 0;
    return 0;
}

static void front_dealloc(ImuFront *s)
{
    for (int i = 0; i < 4; i++)
        Py_CLEAR(s->reasons[i]);
    Py_TYPE(s)->tp_free((PyObject *)s);
}

int uwbd_imu_front_ready(void)
{
    return PyType_Ready(&UwbdImuFrontType);
}

#define METHOD(name, doc) {#name, (PyCFunction)(void (*)(void))front_##name, METH_FASTCALL, doc}

static PyMethodDef front_methods[] = {
    METHOD(judge, "judge(t_ns, acc, gyro) -> '' when the sample may be used, else the reason."),
    METHOD(burst_s, "burst_s(t_ns): how long samples have been rejected without a break."),
    METHOD(step_many, "step_many(state, samples, last_ns, state_ns, max_gap_s, "
                      "propagate_every_s) -> (rows, reason): the common samples of a read "
                      "judged, mapped and integrated."),
    {NULL, NULL, 0, NULL},
};

static PyGetSetDef front_getset[] = {
    {"last_good", (getter)get_last_good, NULL, "The last accepted (acc, gyro), sensor axes.",
     NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

PyTypeObject UwbdImuFrontType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "uwbd.fusion.core._core.ImuFront",
    .tp_doc = "The IMU front: ImuCheck's screen, to_body's maps, the common sample integrated.",
    .tp_basicsize = sizeof(ImuFront),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)front_init,
    .tp_dealloc = (destructor)front_dealloc,
    .tp_methods = front_methods,
    .tp_getset = front_getset,
};
