/* uwbd.fusion._core.pose_step: the common pose, whole, in one call.
 *
 * Almost every pose is asked of a filter that is tracking (or aligning) with nothing
 * wrong: Filter.pose then takes the numbers (pose_numbers), the health monitor's verdict
 * (HealthMonitor.assess: no fault, no note), its summary (the phase's name) and makes the
 * Pose. pose_step does the same on the same attributes, with the same arithmetic, and
 * declines (returns NotImplemented, having changed nothing) for anything else: no filter,
 * a number not finite (the reference restarts), any fault or note, coasting, a time
 * difference too large to be exact as a double. Filter.pose then takes it: it stays the
 * reference.
 *
 *   pose_step(parts) -> Pose | NotImplemented
 * parts: Filter._pose_parts, in the order of the enum below.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>

#include "../_tuple.h"
#include "_core.h"

enum {
    Q_FILTER, Q_MONITOR, Q_NUMBERS, Q_POSE, Q_HEALTH, Q_TRACKING, Q_ALIGNING,
    Q_TRACKING_TEXT, Q_ALIGNING_TEXT, Q_COUNT
};
enum { L_HOLD_NS, L_TIMEOUT, L_MAX_SIGMA, L_COAST, L_MAX_YAW, L_COUNT }; /* floats */
enum { H_PHASE, H_FAULTS, H_NOTES, H_SINCE, H_SIGMA, H_RESETS, H_RESET_T, H_REASON, H_JUMP,
       H_COUNT };
enum { POSE_T, POSE_P, POSE_V, POSE_Q, POSE_COV, POSE_STATUS, POSE_OBSERVABLE, POSE_HEALTH,
       POSE_COUNT };
#define EXACT (INT64_C(1) << 52) /* differences below this are exact as doubles */
enum {
    S_NUMERICAL_NS, S_IMU_FAULT_NS, S_INCONSISTENT_SINCE_NS, S_IMU_GAP, S_REJUDGING,
    S_MIRROR_UNRESOLVED, S_LAST_RANGE_NS, S_RESETS, S_LAST_RESET, S_EKF, S_T_NS, S_ALIGNED,
    S_P_MATRIX, S_Q, S_P, S_V, S_COUNT
};
static const char *const text[S_COUNT] = {
    "_numerical_ns", "_imu_fault_ns", "_inconsistent_since_ns", "imu_gap", "_rejudging",
    "mirror_unresolved", "last_range_ns", "resets", "last_reset", "ekf", "t_ns", "_aligned",
    "P", "q", "p", "v",
};
static PyObject *str[S_COUNT];

int uwbd_pose_init(void)
{
    return uwbd_intern(text, str, S_COUNT);
}

/* ns[name], borrowed; NULL when absent (an error cleared: the caller declines) */
static PyObject *get(PyObject *ns, int name)
{
    PyObject *v = PyDict_GetItemWithError(ns, str[name]);
    if (v == NULL)
        PyErr_Clear();
    return v;
}

/* the time since `name` (an int) is below hold_ns (a float) as Python compares them: 1 yes,
 * 0 no or None, -1 not exact (decline), -2 an error */
static int within(PyObject *ns, int name, int64_t t, double hold_ns)
{
    PyObject *v = get(ns, name); /* (a missing one: None) */
    if (v == NULL || v == Py_None)
        return 0;
    int64_t x;
    int none;
    int ok = uwbd_as_i64(v, &x, &none);
    if (ok < 0)
        return -2;
    if (ok == 0 || t - x >= EXACT || x - t >= EXACT)
        return -1;
    return (double)(t - x) < hold_ns;
}

/* HealthMonitor.assess(t, True, observable, sigma, True) when it finds no fault and no
 * note, and the phase is tracking or aligning: the Health; NotImplemented otherwise. */
static PyObject *health(PyObject *const *parts, int64_t t, const double *c, int observable,
                        double sigma)
{
    PyObject *m = parts[Q_MONITOR];
    int a = within(m, S_NUMERICAL_NS, t, c[L_HOLD_NS]);
    int b = a != 0 ? a : within(m, S_IMU_FAULT_NS, t, c[L_HOLD_NS]);
    if (b == -2)
        return NULL;
    PyObject *inconsistent = get(m, S_INCONSISTENT_SINCE_NS);
    PyObject *gap = get(m, S_IMU_GAP);
    PyObject *rejudging = get(m, S_REJUDGING);
    PyObject *unresolved = get(m, S_MIRROR_UNRESOLVED);
    PyObject *last = get(m, S_LAST_RANGE_NS);
    PyObject *resets = get(m, S_RESETS);
    PyObject *reset = get(m, S_LAST_RESET);
    if (b != 0 || inconsistent != Py_None || gap != Py_False || rejudging != Py_False ||
        unresolved != Py_False || last == NULL || last == Py_None || resets == NULL ||
        reset == NULL || !(sigma <= c[L_MAX_SIGMA]))
        return Py_NewRef(Py_NotImplemented);
    int64_t x;
    int none;
    int ok = uwbd_as_i64(last, &x, &none);
    if (ok < 0)
        return NULL;
    if (ok == 0 || t - x >= EXACT || x - t >= EXACT)
        return Py_NewRef(Py_NotImplemented);
    double since = (double)(t - x) / 1e9;
    if (since > c[L_TIMEOUT] || since > c[L_COAST])
        return Py_NewRef(Py_NotImplemented); /* a fault, or coasting */
    PyObject *reset_t = Py_None, *reason = NULL, *jump = Py_None;
    if (reset != Py_None) {
        if (!PyTuple_CheckExact(reset) || PyTuple_GET_SIZE(reset) != 3)
            return Py_NewRef(Py_NotImplemented);
        reset_t = PyTuple_GET_ITEM(reset, 0);
        reason = PyTuple_GET_ITEM(reset, 1);
        jump = PyTuple_GET_ITEM(reset, 2);
    }
    PyObject *items[H_COUNT] = {
        Py_NewRef(parts[observable ? Q_TRACKING : Q_ALIGNING]), PyTuple_New(0),
        PyTuple_New(0), PyFloat_FromDouble(since), PyFloat_FromDouble(sigma),
        Py_NewRef(resets), Py_NewRef(reset_t),
        reason == NULL ? PyUnicode_FromStringAndSize(NULL, 0) : Py_NewRef(reason),
        Py_NewRef(jump)};
    return uwbd_tuple_of((PyTypeObject *)parts[Q_HEALTH], items, H_COUNT);
}

/* pose_step(parts) -> Pose | NotImplemented (see the top of this file) */
PyObject *uwbd_pose_step(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 1 || !PyTuple_Check(args[0]) || PyTuple_GET_SIZE(args[0]) != Q_COUNT ||
        !PyTuple_Check(PyTuple_GET_ITEM(args[0], Q_NUMBERS)) ||
        PyTuple_GET_SIZE(PyTuple_GET_ITEM(args[0], Q_NUMBERS)) != L_COUNT ||
        !PyType_Check(PyTuple_GET_ITEM(args[0], Q_POSE)) ||
        !PyType_Check(PyTuple_GET_ITEM(args[0], Q_HEALTH))) {
        PyErr_SetString(PyExc_TypeError, "pose_step(parts): parts as Filter makes them");
        return NULL;
    }
    PyObject *const *parts = &PyTuple_GET_ITEM(args[0], 0);
    double c[L_COUNT];
    if (uwbd_doubles_of(parts[Q_NUMBERS], c, L_COUNT) < 0)
        return NULL;
    PyObject *f = parts[Q_FILTER];
    PyObject *ekf = get(f, S_EKF), *t_obj = get(f, S_T_NS);
    PyObject *aligned = get(f, S_ALIGNED);
    int64_t t;
    int none;
    if (ekf == NULL || ekf == Py_None || t_obj == NULL || aligned == NULL ||
        uwbd_as_i64(t_obj, &t, &none) != 1 || none) {
        PyErr_Clear();
        return Py_NewRef(Py_NotImplemented);
    }
    PyObject *ns = PyObject_GenericGetDict(ekf, NULL);
    if (ns == NULL)
        return NULL;
    PyObject *P = get(ns, S_P_MATRIX), *q = get(ns, S_Q);
    PyObject *p = get(ns, S_P), *v = get(ns, S_V);
    PyObject *yaw = PyFloat_FromDouble(c[L_MAX_YAW]), *numbers = NULL, *out = NULL;
    if (yaw == NULL)
        goto done;
    if (P == NULL || q == NULL || p == NULL || v == NULL)
        goto decline;
    PyObject *nargs_[6] = {P, q, p, v, aligned, yaw};
    numbers = uwbd_pose_numbers(NULL, nargs_, 6);
    if (numbers == NULL) { /* P not C-contiguous (np.ascontiguousarray would make another),
                            * or anything odd: Python's, which says so itself */
        PyErr_Clear();
        goto decline;
    }
    if (numbers == Py_None || !PyTuple_Check(numbers) || PyTuple_GET_SIZE(numbers) != 6)
        goto decline; /* not finite: the reference restarts */
    int observable = PyTuple_GET_ITEM(numbers, 2) == Py_True;
    double sigma = PyFloat_AsDouble(PyTuple_GET_ITEM(numbers, 1));
    PyObject *h = health(parts, t, c, observable, sigma);
    if (h == NULL || h == Py_NotImplemented) {
        out = h;
        goto done;
    }
    PyObject *items[POSE_COUNT] = {
        Py_NewRef(t_obj), Py_NewRef(PyTuple_GET_ITEM(numbers, 3)),
        Py_NewRef(PyTuple_GET_ITEM(numbers, 4)), Py_NewRef(PyTuple_GET_ITEM(numbers, 5)),
        Py_NewRef(PyTuple_GET_ITEM(numbers, 0)),
        Py_NewRef(parts[observable ? Q_TRACKING_TEXT : Q_ALIGNING_TEXT]),
        Py_NewRef(observable ? Py_True : Py_False), h};
    out = uwbd_tuple_of((PyTypeObject *)parts[Q_POSE], items, POSE_COUNT);
    goto done;
decline:
    out = Py_NewRef(Py_NotImplemented);
done:
    Py_XDECREF(yaw);
    Py_XDECREF(numbers);
    Py_DECREF(ns);
    return out;
}
