/* uwbd.fusion._core.epoch_step: the common UWB message, whole, in one call.
 *
 * Almost every UWB message reaches a filter that is running and tightly coupled, with
 * every range sound and to a configured anchor: Filter._update then gates the ranges
 * (gating.gate), resolves their anchors (Filter._resolve), keeps them (RangeWindow.add),
 * while aligning makes the message's fix (_epoch_fix), brings the state to the message
 * (_predict_to, propagate, take_epoch), holds the heading while aligning (_hold_heading),
 * tracks the UWB stillness (_track_fixes), adds the constraint rows when due
 * (_constraints), fuses the epoch (_fuse_epoch: Eskf.fuse_ranges, the rows' outcomes, the
 * covariance kept sane), fades (_fade) and checks for divergence (_check_divergence).
 * epoch_step does the same, in that order, on the same attributes, with the same
 * arithmetic (the same bits); the rarer branches on the way (the fix and the held heading
 * while aligning, a stillness fix due, the constraint rows, a side flipped by the fix, an
 * inconsistent or diverged state, a covariance out of bounds, a fuse the C core declines,
 * outcomes it does not expect) it calls the Python methods for, so that the Python code
 * stays the reference of every step.
 *
 * It declines (returns None, having changed nothing) before its first write for anything
 * else: a range the gate or the resolver would say anything about, a first message, a
 * filter waiting, coasting, re-levelling or recording, a late message, a side flipped
 * before, the anchors' arrays not made yet; Filter._update then takes the message.
 *
 *   epoch_step(parts, uwb) -> [FusionReport] | None
 * parts: Filter._epoch_parts, in the order of the enum below.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "_core.h"

enum {
    E_FILTER, E_GATING, E_MONITOR, E_STILL_FIXES, E_LATEST, E_CONFIGURED, E_RESOLVED,
    E_POLICIES, E_EMPTY_ROWS, E_RANGE_KEYS, E_OUTCOME_PARTS, E_KNOWN, E_MAX_SIGMA, E_NUMBERS,
    E_CALLS, E_COUNT
};
enum {  /* parts[E_NUMBERS]: floats */
    K_MIN_ANCHORS, K_MIN_RANGE, K_MAX_RANGE, K_MAX_GAP, K_MIN_PROPAGATE, K_CONSTRAINT_NS,
    K_STILL_EVERY_NS, K_STILL_NS, K_RANGE_VAR, K_LEVER, K_AUX_SIGMA = K_LEVER + 3,
    K_ATTITUDE, K_GYRO_BIAS_END, K_IMU_BIAS_END, K_COUNT
};
enum {  /* parts[E_CALLS] */
    C_TRACK_FIXES, C_CONSTRAINTS, C_FUSE_EPOCH, C_FADE, C_CHECK_DIVERGENCE, C_KEEP_SANE,
    C_ROW_POLICY, C_NO_ROWS, C_STACK, C_RANGE_KEYS, C_ROW_OUTCOMES, C_ZEROS, C_ARRAY,
    C_EPOCH_FIX, C_FUSE_MESSAGE, C_HOLD_HEADING, C_COUNT
};
#define MAX_K 64                   /* more ranges in one message: Python's */
#define EXACT (INT64_C(1) << 52)   /* differences below this are exact as doubles */
#define HUGE_ENTRY 1e300           /* below this, no sum of the state's numbers overflows */

enum {
    N_T_NS, N_RANGES, N_ANCHOR_ID, N_RANGE_M, N_QUALITY, N_FIRST_T, N_EKF, N_ALIGNED, N_RECORDS,
    N_RELEVEL, N_GOOD_T, N_LAST_IMU, N_CONSTRAINTS_NS, N_FADE_NS, N_MIRROR, N_RANGE_COLUMNS,
    N_COASTED, N_LAST_GOOD_P, N_EPOCHS, N_PASSED, N_FLIPPED, N_RESOLVED, N_MIRROR_UNRESOLVED,
    N_IMU_GAP, N_SINCE, N_C_CORE, N_P_MATRIX, N_B_R, N_P, N_V, N_Q, N_BG, N_BA, N_DV,
    N_PROPAGATED, N_PHI, N_I_CORE, N_DECAY, N_NO_DECAY, N_LAST_DX, N_CLAMP_KEY, N_CLAMP_LIMIT,
    N_PROPAGATE, N_COPY, N_POPLEFT, N_AT_REST, N_KEEP, N_COUNT
};
static const char *const name_text[N_COUNT] = {
    "t_ns", "ranges", "anchor_id", "range_m", "quality", "_first_t_ns", "ekf", "_aligned",
    "records", "_relevel", "_good_imu_ns", "_last_imu", "_constraints_ns", "_fade_ns", "mirror",
    "_range_columns", "_coasted", "_last_good_P", "epochs_passed", "ranges_passed", "flipped",
    "resolved", "mirror_unresolved", "imu_gap", "_inconsistent_since_ns", "_core", "P", "b_r",
    "p", "v", "q", "b_g", "b_a", "_dv_epoch", "_epoch_propagated", "_Phi_epoch", "_I_core",
    "_decay_epoch", "_no_decay", "last_dx", "_clamp_key", "_clamp_limit", "propagate", "copy",
    "popleft", "_at_rest", "keep_transition",
};
static PyObject *names[N_COUNT];
static PyObject *empty_tuple;

int uwbd_epoch_init(void)
{
    if (uwbd_intern(name_text, names, N_COUNT) < 0)
        return -1;
    return (empty_tuple = PyTuple_New(0)) == NULL ? -1 : 0;
}

/* Borrowed: ns[name], or NULL with AttributeError set (every name here is a plain instance
 * attribute its class's __init__ sets: a missing one is a bug). */
static PyObject *attr(PyObject *ns, int name)
{
    PyObject *v = PyDict_GetItemWithError(ns, names[name]);
    if (v == NULL && !PyErr_Occurred())
        PyErr_Format(PyExc_AttributeError, "epoch_step: no attribute %s", name_text[name]);
    return v;
}

static int set_attr(PyObject *ns, int name, PyObject *value)
{
    return PyDict_SetItem(ns, names[name], value);
}

/* ns[name] + k (Python ints) stored back: 0, or -1 with an error set */
static int add_to(PyObject *ns, int name, Py_ssize_t k)
{
    PyObject *v = attr(ns, name);
    if (v == NULL)
        return -1;
    PyObject *step = PyLong_FromSsize_t(k);
    PyObject *sum = step == NULL ? NULL : PyNumber_Add(v, step);
    Py_XDECREF(step);
    int rc = sum == NULL ? -1 : set_attr(ns, name, sum);
    Py_XDECREF(sum);
    return rc;
}

/* A message taken: what the checks read (new references where held). */
typedef struct {
    int64_t t, state_t;
    Py_ssize_t k;
    double r[MAX_K], acc[3], gyro[3];
    PyObject *ids;      /* the anchor ids, a list */
    PyObject *key;      /* tuple(ids) */
    PyObject *arrays;   /* Filter._resolved[key]: (anchors, ones) */
    Py_buffer view;     /* of the anchors array (held while view_held) */
    int view_held;
    const double *anchors; /* its k×3 floats */
    PyObject *ekf, *ekf_ns;
    UwbdNominal nom;    /* the Eskf's nominal state */
    int aligned, due;
    PyObject *fix;      /* the message's fix while aligning (_epoch_fix), else None */
    PyObject *dv;       /* take_epoch's Σ R f Δt (the list it was), for the held heading */
    PyObject *ranges;   /* np.array of the ranges, made when a Python step wants it */
} Take;

static void release(Take *m)
{
    Py_CLEAR(m->ids);
    Py_CLEAR(m->key);
    Py_CLEAR(m->arrays);
    Py_CLEAR(m->ekf);
    Py_CLEAR(m->ekf_ns);
    uwbd_nominal_release(&m->nom);
    Py_CLEAR(m->ranges);
    if (m->view_held)
        PyBuffer_Release(&m->view);
    m->view_held = 0;
    Py_CLEAR(m->fix);
    Py_CLEAR(m->dv);
}

/* ns[name] as an int (1), not one within bounds (0: decline), -1 an error */
static int attr_int(PyObject *ns, int name, int64_t *out)
{
    PyObject *v = attr(ns, name);
    int none;
    if (v == NULL)
        return -1;
    int t = uwbd_as_i64(v, out, &none);
    return t < 0 ? -1 : t == 1 && !none;
}

/* gating.gate and Filter._resolve on the message: every range passes, none has a quality,
 * each is to a configured anchor, and their arrays are made (1); else 0, -1 an error. */
static int ranges_take(PyObject *const *parts, PyObject *uwb, const double *c, Take *m)
{
    PyObject *ranges = PyObject_GetAttr(uwb, names[N_RANGES]);
    if (ranges == NULL)
        return -1;
    int t = 0;
    Py_ssize_t k = PyTuple_CheckExact(ranges) ? PyTuple_GET_SIZE(ranges) : 0;
    long long seen[MAX_K];
    if (k == 0 || k > MAX_K || (double)k < c[K_MIN_ANCHORS])
        goto done;
    if ((m->ids = PyList_New(k)) == NULL || (m->key = PyTuple_New(k)) == NULL) {
        t = -1;
        goto done;
    }
    for (Py_ssize_t i = 0; i < k; i++) {
        PyObject *r = PyTuple_GET_ITEM(ranges, i);
        PyObject *id = PyObject_GetAttr(r, names[N_ANCHOR_ID]);
        PyObject *range = id == NULL ? NULL : PyObject_GetAttr(r, names[N_RANGE_M]);
        PyObject *quality = range == NULL ? NULL : PyObject_GetAttr(r, names[N_QUALITY]);
        if (quality == NULL) {
            Py_XDECREF(id);
            Py_XDECREF(range);
            t = -1;
            goto done;
        }
        int overflow = 0;
        long long a = PyLong_CheckExact(id) ? PyLong_AsLongLongAndOverflow(id, &overflow) : 0;
        int ok = PyLong_CheckExact(id) && !overflow && PyFloat_CheckExact(range) &&
                 quality == Py_None;
        double d = ok ? PyFloat_AS_DOUBLE(range) : 0.0;
        Py_DECREF(range);
        Py_DECREF(quality);
        /* _judge: finite, not negative, within the limits (a NaN fails every test) */
        ok = ok && isfinite(d) && d >= 0.0 && !(d < c[K_MIN_RANGE]) && !(d > c[K_MAX_RANGE]);
        for (Py_ssize_t j = 0; ok && j < i; j++)
            ok = seen[j] != a;
        PyObject *known = parts[E_KNOWN];
        int known_ok = !ok || known == Py_None ? 1 : PySequence_Contains(known, id);
        PyObject *pos = !ok || known_ok <= 0 ? NULL
                                             : PyDict_GetItemWithError(parts[E_CONFIGURED], id);
        PyList_SET_ITEM(m->ids, i, id); /* (steals id) */
        Py_INCREF(id);
        PyTuple_SET_ITEM(m->key, i, id);
        if (known_ok < 0 || PyErr_Occurred()) {
            t = -1;
            goto done;
        }
        if (!ok || !known_ok || pos == NULL)
            goto done;
        seen[i] = a;
        m->r[i] = d;
    }
    m->k = k;
    m->arrays = PyDict_GetItemWithError(parts[E_RESOLVED], m->key);
    if (m->arrays == NULL) {
        t = PyErr_Occurred() ? -1 : 0;
        goto done;
    }
    Py_INCREF(m->arrays);
    t = PyTuple_Check(m->arrays) && PyTuple_GET_SIZE(m->arrays) == 2;
    if (t) { /* the anchors k×3 floats, as Filter._resolve makes them (else Python's) */
        if (PyObject_GetBuffer(PyTuple_GET_ITEM(m->arrays, 0), &m->view,
                               PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) {
            PyErr_Clear();
            t = 0;
        } else {
            m->view_held = 1;
            t = m->view.len == k * 3 * 8 && m->view.format != NULL &&
                strcmp(m->view.format, "d") == 0;
            m->anchors = (const double *)m->view.buf;
        }
    }
done:
    Py_DECREF(ranges);
    return t;
}

/* The filter's side: running, not recording, the message in order, the IMU fresh
 * (_predict_to holds the last sample), the side not flipped, the state as Eskf.predict
 * reads it. 1, 0 or -1 as above; everything is read and nothing written. */
static int filter_take(PyObject *const *parts, const double *c, Take *m)
{
    PyObject *f = parts[E_FILTER], *v;
    int64_t x;
    int t;
    if ((v = attr(f, N_FIRST_T)) == NULL || (t = v != Py_None) <= 0 ||
        (v = attr(f, N_ALIGNED)) == NULL || (t = v == Py_True || v == Py_False) <= 0 ||
        (v = attr(f, N_RECORDS)) == NULL || (t = v == Py_None) <= 0 ||
        (v = attr(f, N_RELEVEL)) == NULL || (t = v == Py_None) <= 0)
        return v == NULL ? -1 : 0;
    m->aligned = attr(f, N_ALIGNED) == Py_True;
    if ((t = attr_int(f, N_T_NS, &m->state_t)) <= 0)
        return t;
    if (m->t < m->state_t || m->t - m->state_t >= EXACT)
        return 0; /* late (counted by Python), or far ahead */
    if ((t = attr_int(f, N_GOOD_T, &x)) <= 0)
        return t;
    if (m->t - x >= EXACT || x - m->t >= EXACT || (double)(m->t - x) / 1e9 > c[K_MAX_GAP])
        return 0; /* the IMU is not fresh: coasted by Python */
    PyObject *last = attr(f, N_LAST_IMU);
    if (last == NULL)
        return -1;
    if (!PyTuple_CheckExact(last) || PyTuple_GET_SIZE(last) != 2 ||
        !uwbd_floats_of(PyTuple_GET_ITEM(last, 0), m->acc, 3, 0) ||
        !uwbd_floats_of(PyTuple_GET_ITEM(last, 1), m->gyro, 3, 0))
        return 0;
    PyObject *mirror = attr(f, N_MIRROR);
    if (mirror == NULL)
        return -1;
    PyObject *flipped = PyObject_GetAttr(mirror, names[N_FLIPPED]);
    if (flipped == NULL)
        return -1;
    t = flipped == Py_False;
    Py_DECREF(flipped);
    if (!t)
        return 0;
    /* the constraint rows due (t_ns - _constraints_ns >= every, the start value -2^63) */
    PyObject *cns = attr(f, N_CONSTRAINTS_NS);
    if (cns == NULL)
        return -1;
    int overflow = 0;
    long long since = PyLong_CheckExact(cns) ? PyLong_AsLongLongAndOverflow(cns, &overflow) : 0;
    if (!PyLong_CheckExact(cns) || overflow || (since == -1 && PyErr_Occurred()))
        return PyErr_Occurred() ? -1 : 0;
    m->due = since <= m->t - (int64_t)c[K_CONSTRAINT_NS];
    /* the running filter's Eskf, on the C core */
    if ((m->ekf = attr(f, N_EKF)) == NULL)
        return -1;
    Py_INCREF(m->ekf);
    if (m->ekf == Py_None)
        return 0;
    if ((m->ekf_ns = PyObject_GenericGetDict(m->ekf, NULL)) == NULL)
        return -1;
    if ((v = attr(m->ekf_ns, N_C_CORE)) == NULL)
        return -1;
    if (v == Py_None)
        return 0;
    return uwbd_nominal_read(m->ekf_ns, &m->nom);
}

/* -- the writes, in Filter._update's order ---------------------------------------------- */

/* gate's counters, RangeWindow.add: 0, or -1 with an error set */
static int keep_ranges(PyObject *const *parts, PyObject *t_obj, Take *m)
{
    PyObject *gating = parts[E_GATING];
    if (add_to(gating, N_EPOCHS, 1) < 0 || add_to(gating, N_PASSED, m->k) < 0)
        return -1;
    const double *a = m->anchors;
    int rc = 0;
    for (Py_ssize_t i = 0; i < m->k && rc == 0; i++) {
        PyObject *pos = uwbd_floats(a + 3 * i, 3, 1);
        PyObject *r = pos == NULL ? NULL : PyFloat_FromDouble(m->r[i]);
        PyObject *item = r == NULL ? NULL : PyTuple_Pack(3, t_obj, pos, r);
        rc = item == NULL ? -1
                          : PyDict_SetItem(parts[E_LATEST], PyList_GET_ITEM(m->ids, i), item);
        Py_XDECREF(pos);
        Py_XDECREF(r);
        Py_XDECREF(item);
    }
    return rc;
}

/* The side's note (monitor.mirror_unresolved = mirror.unresolved), after the fix */
static int note_side(PyObject *const *parts)
{
    PyObject *mirror = attr(parts[E_FILTER], N_MIRROR);
    PyObject *resolved = mirror == NULL ? NULL : PyObject_GetAttr(mirror, names[N_RESOLVED]);
    int yes = resolved == NULL ? -1 : PyObject_IsTrue(resolved);
    Py_XDECREF(resolved);
    return yes < 0 ? -1
                   : set_attr(parts[E_MONITOR], N_MIRROR_UNRESOLVED, yes ? Py_False : Py_True);
}

/* _predict_to (the IMU fresh), then the propagation if due and take_epoch(False) */
static int predict_to(PyObject *const *parts, PyObject *t_obj, const double *c, Take *m)
{
    PyObject *e = m->ekf_ns;
    double dt = (double)(m->t - m->state_t) / 1e9;
    double interval = m->nom.interval;
    if (dt > 0) {
        if (uwbd_nominal_predict(&m->nom, e, m->acc, m->gyro, dt, &interval) < 0 ||
            set_attr(parts[E_MONITOR], N_IMU_GAP, Py_False) < 0 ||
            set_attr(parts[E_FILTER], N_T_NS, t_obj) < 0)
            return -1;
    }
    if (interval >= c[K_MIN_PROPAGATE] || !m->aligned) {
        int done = uwbd_propagate(e);
        if (done == 0) { /* not the C core's case: the method */
            PyObject *rc = PyObject_CallMethodNoArgs(m->ekf, names[N_PROPAGATE]);
            if (rc == NULL)
                return -1;
            Py_DECREF(rc);
        } else if (done < 0) {
            return -1;
        }
    }
    /* take_epoch(False): Σ R f Δt restarted (what it was kept for the held heading); Φ and
     * the decays too, once propagated */
    if ((m->dv = attr(e, N_DV)) == NULL)
        return -1;
    Py_INCREF(m->dv);
    double zero[3] = {0.0, 0.0, 0.0};
    PyObject *dv = uwbd_floats(zero, 3, 1);
    int failed = dv == NULL || set_attr(e, N_DV, dv) < 0;
    Py_XDECREF(dv);
    if (failed)
        return -1;
    PyObject *propagated = attr(e, N_PROPAGATED);
    int yes = propagated == NULL ? -1 : PyObject_IsTrue(propagated);
    if (yes <= 0)
        return yes;
    if (set_attr(e, N_PROPAGATED, Py_False) < 0)
        return -1;
    PyObject *keep = attr(e, N_KEEP); /* Φ and the decays kept (else identity and ones) */
    if (keep == NULL || (yes = PyObject_IsTrue(keep)) <= 0)
        return keep == NULL ? -1 : yes;
    const int from[2] = {N_I_CORE, N_NO_DECAY}, to[2] = {N_PHI, N_DECAY};
    for (int i = 0; i < 2; i++) {
        PyObject *src = attr(e, from[i]);
        PyObject *copy = src == NULL ? NULL : PyObject_CallMethodNoArgs(src, names[N_COPY]);
        int rc = copy == NULL ? -1 : set_attr(e, to[i], copy);
        Py_XDECREF(copy);
        if (rc < 0)
            return -1;
    }
    return 0;
}

/* The ranges as Filter._resolve makes them (np.array), once a Python step wants them. */
static PyObject *ranges_array(PyObject *const *calls, Take *m)
{
    if (m->ranges == NULL) {
        PyObject *list = uwbd_floats(m->r, m->k, 1);
        if (list == NULL)
            return NULL;
        m->ranges = PyObject_CallOneArg(calls[C_ARRAY], list);
        Py_DECREF(list);
    }
    return m->ranges;
}

/* calls[which](t_ns, ids, anchors, ranges[, more...]): new, or NULL with an error set */
static PyObject *call_with_epoch(PyObject *const *calls, int which, PyObject *t_obj, Take *m,
                                 PyObject *more1, PyObject *more2, PyObject *more3)
{
    PyObject *ranges = ranges_array(calls, m);
    if (ranges == NULL)
        return NULL;
    PyObject *args[7] = {t_obj, m->ids, PyTuple_GET_ITEM(m->arrays, 0), ranges, more1, more2,
                         more3};
    size_t n = 4 + (more1 != NULL) + (more2 != NULL) + (more3 != NULL);
    return PyObject_Vectorcall(calls[which], args, n, NULL);
}

/* _track_fixes: a fix when the stillness wants one (Python's), else forget_before */
static int track_fixes(PyObject *const *parts, PyObject *t_obj, const double *c, Take *m)
{
    PyObject *fixes = parts[E_STILL_FIXES];
    Py_ssize_t n = PyObject_Length(fixes);
    if (n < 0)
        return -1;
    int wants = n == 0;
    if (!wants) {
        PyObject *last = PySequence_GetItem(fixes, n - 1);
        int64_t x;
        int t = last == NULL ? -1
                : !PyTuple_Check(last) || PyTuple_GET_SIZE(last) < 1 ? 0
                : uwbd_as_i64(PyTuple_GET_ITEM(last, 0), &x, NULL);
        Py_XDECREF(last);
        if (t < 0)
            return -1;
        wants = t == 0 || m->t - x >= (int64_t)c[K_STILL_EVERY_NS];
    }
    if (wants) { /* (and a fix time not as expected: Python's own) */
        PyObject *rc = call_with_epoch(&PyTuple_GET_ITEM(parts[E_CALLS], 0), C_TRACK_FIXES,
                                       t_obj, m, m->fix, NULL, NULL);
        Py_XDECREF(rc);
        return rc == NULL ? -1 : 0;
    }
    /* UwbStillness.forget_before: Python's own comparison of each time with the float */
    PyObject *oldest = PyFloat_FromDouble((double)m->t - c[K_STILL_NS]);
    if (oldest == NULL)
        return -1;
    int rc = 0;
    for (;;) {
        PyObject *first = PyObject_Length(fixes) > 0 ? PySequence_GetItem(fixes, 0) : NULL;
        if (first == NULL) {
            rc = PyErr_Occurred() ? -1 : 0;
            break;
        }
        int older = PyTuple_Check(first) && PyTuple_GET_SIZE(first) > 0
                        ? PyObject_RichCompareBool(PyTuple_GET_ITEM(first, 0), oldest, Py_LT)
                        : -1;
        Py_DECREF(first);
        if (older < 0 && !PyErr_Occurred())
            PyErr_SetString(PyExc_TypeError, "epoch_step: a stillness fix not (t_ns, p)");
        if (older <= 0) {
            rc = older;
            break;
        }
        PyObject *gone = PyObject_CallMethodNoArgs(fixes, names[N_POPLEFT]);
        if (gone == NULL) {
            rc = -1;
            break;
        }
        Py_DECREF(gone);
    }
    Py_DECREF(oldest);
    return rc;
}

/* The extra rows (Rows: H, y, R, keys) and the update's row policy: new references */
static int extra_rows(PyObject *const *parts, PyObject *const *calls, PyObject *constraints,
                      PyObject *n_obj, Take *m, PyObject **extra, PyObject **keys,
                      PyObject **policy)
{
    int due = PyObject_IsTrue(constraints);
    if (due < 0)
        return -1;
    if (due) {
        *extra = PyObject_CallOneArg(calls[C_STACK], constraints);
    } else {
        *extra = PyDict_GetItemWithError(parts[E_EMPTY_ROWS], n_obj);
        if (*extra != NULL)
            Py_INCREF(*extra);
        else if (!PyErr_Occurred())
            *extra = PyObject_CallOneArg(calls[C_NO_ROWS], n_obj);
    }
    if (*extra == NULL)
        return -1;
    PyObject *more = PyTuple_Check(*extra) && PyTuple_GET_SIZE(*extra) == 4
                         ? PyTuple_GET_ITEM(*extra, 3) : NULL;
    if (more == NULL || !PyList_Check(more)) {
        PyErr_SetString(PyExc_TypeError, "epoch_step: extra rows not (H, y, R, keys)");
        return -1;
    }
    /* range_keys(ids) + extra.keys */
    Py_ssize_t e = PyList_GET_SIZE(more), total = m->k + e;
    if ((*keys = PyList_New(total)) == NULL)
        return -1;
    char kinds[MAX_K + 64];
    for (Py_ssize_t i = 0; i < m->k; i++) {
        PyObject *key = PyDict_GetItemWithError(parts[E_RANGE_KEYS],
                                                PyList_GET_ITEM(m->ids, i));
        if (key == NULL) { /* an anchor's first row: range_keys makes its key */
            if (PyErr_Occurred())
                return -1;
            PyObject *made = PyObject_CallOneArg(calls[C_RANGE_KEYS], m->ids);
            if (made == NULL)
                return -1;
            int ok = PyList_Check(made) && PyList_GET_SIZE(made) == m->k;
            key = ok ? PyList_GET_ITEM(made, i) : NULL;
            Py_XINCREF(key);
            Py_DECREF(made);
            if (key == NULL) {
                PyErr_SetString(PyExc_TypeError, "epoch_step: range_keys not one per range");
                return -1;
            }
            PyList_SET_ITEM(*keys, i, key);
        } else {
            PyList_SET_ITEM(*keys, i, Py_NewRef(key));
        }
        kinds[i] = 'r';
    }
    int plain = total <= (Py_ssize_t)sizeof kinds;
    for (Py_ssize_t i = 0; i < e; i++) {
        PyObject *key = PyList_GET_ITEM(more, i);
        PyList_SET_ITEM(*keys, m->k + i, Py_NewRef(key));
        PyObject *kind = PyTuple_Check(key) && PyTuple_GET_SIZE(key) == 2
                             ? PyTuple_GET_ITEM(key, 0) : NULL;
        Py_UCS4 first = kind != NULL && PyUnicode_Check(kind) && PyUnicode_GET_LENGTH(kind) > 0
                            ? PyUnicode_READ_CHAR(kind, 0) : 0;
        if (plain && first > 0 && first < 128)
            kinds[m->k + i] = (char)first;
        else
            plain = 0;
    }
    /* _row_policy(keys, True): those made before, by their kinds */
    *policy = NULL;
    if (plain) {
        PyObject *text = PyUnicode_FromStringAndSize(kinds, total);
        PyObject *look = text == NULL ? NULL : PyTuple_Pack(2, text, Py_True);
        Py_XDECREF(text);
        if (look == NULL)
            return -1;
        *policy = PyDict_GetItemWithError(parts[E_POLICIES], look);
        Py_DECREF(look);
        Py_XINCREF(*policy);
        if (*policy == NULL && PyErr_Occurred())
            return -1;
    }
    if (*policy == NULL) {
        PyObject *args[2] = {*keys, Py_True};
        *policy = PyObject_Vectorcall(calls[C_ROW_POLICY], args, 2, NULL);
    }
    return *policy == NULL ? -1 : 0;
}

/* The covariance kept within bounds (_keep_covariance_sane: Python's when anything is to
 * be clamped, or the limits not yet made) */
static int keep_sane(PyObject *const *parts, PyObject *const *calls, PyObject *ekf_ns,
                     const double *c)
{
    PyObject *key = attr(ekf_ns, N_CLAMP_KEY), *limit = attr(ekf_ns, N_CLAMP_LIMIT);
    PyObject *P = attr(ekf_ns, N_P_MATRIX);
    if (key == NULL || limit == NULL || P == NULL)
        return -1;
    int out = 1;
    if (PyTuple_Check(key) && PyTuple_GET_SIZE(key) == 2 &&
        PyTuple_GET_ITEM(key, 0) == parts[E_MAX_SIGMA] &&
        PyFloat_CheckExact(PyTuple_GET_ITEM(key, 1)) &&
        PyFloat_AS_DOUBLE(PyTuple_GET_ITEM(key, 1)) == c[K_AUX_SIGMA])
        out = uwbd_diagonal_out_of_bounds(P, limit);
    if (out <= 0)
        return out;
    PyObject *rc = PyObject_CallNoArgs(calls[C_KEEP_SANE]);
    Py_XDECREF(rc);
    return rc == NULL ? -1 : 0;
}

/* _fuse_epoch on the C core: new reports, or NULL with an error set. The fuse itself
 * declined, or the state not as taken (a constraint step restarted the attitude): the
 * Python method, from the start (nothing was changed). */
static PyObject *fuse(PyObject *const *parts, PyObject *t_obj, const double *c, Take *m,
                      PyObject *constraints)
{
    PyObject *const *calls = &PyTuple_GET_ITEM(parts[E_CALLS], 0), *f = parts[E_FILTER];
    PyObject *ekf = attr(f, N_EKF), *v;
    if (ekf == NULL)
        return NULL;
    /* _considered(): the states an update may not correct */
    int64_t good, now;
    int t = ekf == m->ekf;
    int fresh = t && (v = attr(f, N_RELEVEL)) != NULL && v == Py_None
                    ? attr_int(f, N_GOOD_T, &good) : 0;
    if (fresh == 1 && (fresh = attr_int(f, N_T_NS, &now)) == 1)
        fresh = now - good < EXACT && good - now < EXACT &&
                (double)(now - good) / 1e9 <= c[K_MAX_GAP];
    PyObject *aligned = t ? attr(f, N_ALIGNED) : NULL, *at_rest = t ? attr(f, N_AT_REST) : NULL;
    if (fresh < 0 || PyErr_Occurred())
        return NULL;
    int holding = aligned == NULL || at_rest == NULL ? 0
                  : !PyObject_IsTrue(aligned) && !PyObject_IsTrue(at_rest);
    if (PyErr_Occurred())
        return NULL;
    Py_ssize_t c0 = 0, c1 = 0; /* None */
    if (!fresh) {
        c0 = (Py_ssize_t)c[K_ATTITUDE];
        c1 = (Py_ssize_t)c[K_IMU_BIAS_END];
    } else if (holding) {
        c0 = (Py_ssize_t)c[K_ATTITUDE];
        c1 = (Py_ssize_t)c[K_GYRO_BIAS_END];
    }
    PyObject *out = NULL, *extra = NULL, *keys = NULL, *policy = NULL, *dx = NULL;
    /* (held as new references: the Python steps called below may drop theirs) */
    PyObject *columns = NULL, *fused = NULL, *P = t ? attr(m->ekf_ns, N_P_MATRIX) : NULL;
    PyObject *b_r = P == NULL ? NULL : attr(m->ekf_ns, N_B_R);
    PyObject *range_columns = b_r == NULL ? NULL : attr(f, N_RANGE_COLUMNS);
    if (range_columns == NULL) {
        P = b_r = NULL;
        goto python;
    }
    Py_INCREF(P);
    Py_INCREF(b_r);
    Py_INCREF(range_columns);
    /* P as Eskf.fuse_ranges leaves it (np.ascontiguousarray): else Python's */
    Py_buffer view;
    if (PyObject_GetBuffer(P, &view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE) < 0) {
        PyErr_Clear();
        goto python;
    }
    t = view.format != NULL && strcmp(view.format, "d") == 0 && view.ndim == 2;
    PyBuffer_Release(&view);
    if (!t)
        goto python;
    Py_ssize_t n = PyObject_Length(b_r);
    PyObject *n_obj = n < 0 ? NULL : PyLong_FromSsize_t(n + N_CORE);
    if (n_obj == NULL)
        goto done;
    t = extra_rows(parts, calls, constraints, n_obj, m, &extra, &keys, &policy);
    if (t == 0 && (dx = PyObject_CallOneArg(calls[C_ZEROS], n_obj)) == NULL)
        t = -1;
    Py_DECREF(n_obj);
    if (t < 0 || (columns = PyTuple_New(m->k)) == NULL)
        goto done;
    for (Py_ssize_t i = 0; i < m->k; i++) {
        PyObject *cols = PyDict_GetItemWithError(range_columns, PyList_GET_ITEM(m->ids, i));
        if (cols == NULL && PyErr_Occurred())
            goto done;
        PyTuple_SET_ITEM(columns, i, Py_NewRef(cols == NULL ? empty_tuple : cols));
    }
    /* the nominal state now (a propagation or the constraints may have made new lists) */
    PyObject *nominal[5];
    const int which[5] = {N_P, N_V, N_Q, N_BG, N_BA};
    for (int i = 0; i < 5; i++)
        if ((nominal[i] = attr(m->ekf_ns, which[i])) == NULL)
            goto done;
    double var[MAX_K];
    for (Py_ssize_t i = 0; i < m->k; i++)
        var[i] = c[K_RANGE_VAR];
    fused = uwbd_fuse_ranges_on(P, dx, b_r, nominal, c + K_LEVER, m->anchors, m->r, var, m->k,
                                columns, PyTuple_GET_ITEM(extra, 0), PyTuple_GET_ITEM(extra, 1),
                                PyTuple_GET_ITEM(extra, 2), policy, c0, c1);
    if (fused == NULL)
        goto done;
    if (fused == Py_None)
        goto python;
    /* Eskf._taken */
    PyObject *raw = PyTuple_GET_ITEM(fused, 0), *q = PyTuple_GET_ITEM(fused, 1);
    if (q != Py_None && (set_attr(m->ekf_ns, N_Q, q) < 0 || set_attr(m->ekf_ns, N_LAST_DX, dx) < 0))
        goto done;
    /* _outcomes: on the C core, or the reference where it declines */
    PyObject *args[4] = {parts[E_OUTCOME_PARTS], t_obj, keys, raw};
    out = uwbd_outcomes(NULL, args, 4);
    if (out == Py_NotImplemented) {
        Py_DECREF(out);
        out = PyObject_Vectorcall(calls[C_ROW_OUTCOMES], args + 1, 3, NULL);
    }
    if (out != NULL && keep_sane(parts, calls, m->ekf_ns, c) < 0)
        Py_CLEAR(out);
    goto done;
python:
    if (!PyErr_Occurred()) {
        PyObject *ones = PyTuple_GET_ITEM(m->arrays, 1);
        out = call_with_epoch(calls, C_FUSE_EPOCH, t_obj, m, ones, m->fix, constraints);
    }
done:
    Py_XDECREF(P);
    Py_XDECREF(b_r);
    Py_XDECREF(range_columns);
    Py_XDECREF(extra);
    Py_XDECREF(keys);
    Py_XDECREF(policy);
    Py_XDECREF(dx);
    Py_XDECREF(columns);
    Py_XDECREF(fused);
    return out;
}

/* _fade and _check_divergence (Python's when the innovations are inconsistent, or a
 * number of the state is not finite or absurd), then the last good covariance kept */
static int after_fuse(PyObject *const *parts, PyObject *t_obj, Take *m)
{
    PyObject *const *calls = &PyTuple_GET_ITEM(parts[E_CALLS], 0), *f = parts[E_FILTER];
    PyObject *fade_ns = attr(f, N_FADE_NS), *since = attr(parts[E_MONITOR], N_SINCE);
    PyObject *ekf = attr(f, N_EKF);
    if (fade_ns == NULL || since == NULL || ekf == NULL)
        return -1;
    PyObject *rc;
    if (fade_ns != Py_None && ekf != Py_None && since != Py_None) {
        rc = call_with_epoch(calls, C_FADE, t_obj, m, NULL, NULL, NULL);
        if (rc == NULL)
            return -1;
        Py_DECREF(rc);
    } else if (set_attr(f, N_FADE_NS, t_obj) < 0) {
        return -1;
    }
    if ((ekf = attr(f, N_EKF)) == NULL || (since = attr(parts[E_MONITOR], N_SINCE)) == NULL)
        return -1;
    int sound = ekf == m->ekf && since == Py_None;
    PyObject *P = sound ? attr(m->ekf_ns, N_P_MATRIX) : NULL;
    if (sound && P == NULL)
        return -1;
    if (sound) { /* float(np.add.reduce(P)) + sum(p) + sum(v) + sum(q) is finite */
        double x[4];
        const int which[3] = {N_P, N_V, N_Q};
        for (int i = 0; i < 3 && sound; i++) {
            PyObject *v = attr(m->ekf_ns, which[i]);
            if (v == NULL)
                return -1;
            sound = uwbd_floats_of(v, x, which[i] == N_Q ? 4 : 3, 0);
            for (int j = 0; j < (which[i] == N_Q ? 4 : 3) && sound; j++)
                sound = fabs(x[j]) < HUGE_ENTRY;
        }
        if (sound && (sound = uwbd_all_finite_below(P, HUGE_ENTRY)) < 0)
            return -1;
    }
    if (!sound) {
        rc = call_with_epoch(calls, C_CHECK_DIVERGENCE, t_obj, m, NULL, NULL, NULL);
        if (rc == NULL)
            return -1;
        int moved = PyObject_IsTrue(rc);
        Py_DECREF(rc);
        if (moved != 0)
            return moved < 0 ? -1 : 0;
        if ((ekf = attr(f, N_EKF)) == NULL)
            return -1;
        if (ekf == Py_None)
            return 0;
        PyObject *ns = PyObject_GenericGetDict(ekf, NULL);
        P = ns == NULL ? NULL : attr(ns, N_P_MATRIX);
        PyObject *copy = P == NULL ? NULL : PyObject_CallMethodNoArgs(P, names[N_COPY]);
        Py_XDECREF(ns);
        int failed = copy == NULL || set_attr(f, N_LAST_GOOD_P, copy) < 0;
        Py_XDECREF(copy);
        return failed ? -1 : 0;
    }
    PyObject *copy = PyObject_CallMethodNoArgs(P, names[N_COPY]);
    int failed = copy == NULL || set_attr(f, N_LAST_GOOD_P, copy) < 0;
    Py_XDECREF(copy);
    return failed ? -1 : 0;
}

/* epoch_step(parts, uwb) -> [FusionReport] | None (see the top of this file) */
PyObject *uwbd_epoch_step(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 2 || !PyTuple_Check(args[0]) || PyTuple_GET_SIZE(args[0]) != E_COUNT ||
        !PyTuple_Check(PyTuple_GET_ITEM(args[0], E_NUMBERS)) ||
        PyTuple_GET_SIZE(PyTuple_GET_ITEM(args[0], E_NUMBERS)) != K_COUNT ||
        !PyTuple_Check(PyTuple_GET_ITEM(args[0], E_CALLS)) ||
        PyTuple_GET_SIZE(PyTuple_GET_ITEM(args[0], E_CALLS)) != C_COUNT) {
        PyErr_SetString(PyExc_TypeError, "epoch_step(parts, uwb): parts as Filter makes them");
        return NULL;
    }
    PyObject *const *parts = &PyTuple_GET_ITEM(args[0], 0);
    double c[K_COUNT];
    if (uwbd_doubles_of(parts[E_NUMBERS], c, K_COUNT) < 0)
        return NULL;
    Take m = {0};
    PyObject *t_obj = PyObject_GetAttr(args[1], names[N_T_NS]), *out = NULL;
    if (t_obj == NULL)
        return NULL;
    int t = uwbd_as_i64(t_obj, &m.t, NULL);
    if (t == 1)
        t = filter_take(parts, c, &m);
    if (t == 1)
        t = ranges_take(parts, args[1], c, &m);
    if (t <= 0) {
        out = t < 0 ? NULL : Py_NewRef(Py_None);
        goto done;
    }
    /* Taken: from here on, the writes and the steps, in Filter._update's order. */
    PyObject *const *calls = &PyTuple_GET_ITEM(parts[E_CALLS], 0);
    m.fix = Py_NewRef(Py_None);
    if (keep_ranges(parts, t_obj, &m) < 0)
        goto done;
    if (!m.aligned) { /* the fix (Python's); a side it flipped: the rest is Python's too */
        Py_SETREF(m.fix, call_with_epoch(calls, C_EPOCH_FIX, t_obj, &m, NULL, NULL, NULL));
        PyObject *mirror = m.fix == NULL ? NULL : attr(parts[E_FILTER], N_MIRROR);
        PyObject *flipped = mirror == NULL ? NULL : PyObject_GetAttr(mirror, names[N_FLIPPED]);
        if (flipped == NULL)
            goto done;
        int same = flipped == Py_False;
        Py_DECREF(flipped);
        if (!same) {
            PyObject *none_yet = PyList_New(0);
            out = none_yet == NULL ? NULL
                  : call_with_epoch(calls, C_FUSE_MESSAGE, t_obj, &m,
                                    PyTuple_GET_ITEM(m.arrays, 1), m.fix, none_yet);
            Py_XDECREF(none_yet);
            goto done;
        }
    }
    if (note_side(parts) < 0 || predict_to(parts, t_obj, c, &m) < 0 ||
        set_attr(parts[E_FILTER], N_COASTED, Py_False) < 0)
        goto done;
    if (!m.aligned) { /* _hold_heading(t_ns, (dv[0], dv[1], dv[2]), fix), as take_epoch */
        PyObject *items[3] = {NULL, NULL, NULL}, *dv = NULL;
        for (int i = 0; i < 3 && (i == 0 || items[i - 1] != NULL); i++)
            items[i] = PySequence_GetItem(m.dv, i);
        if (items[2] != NULL)
            dv = PyTuple_Pack(3, items[0], items[1], items[2]);
        for (int i = 0; i < 3; i++)
            Py_XDECREF(items[i]);
        PyObject *args_[3] = {t_obj, dv, m.fix};
        PyObject *rc = dv == NULL ? NULL
                       : PyObject_Vectorcall(calls[C_HOLD_HEADING], args_, 3, NULL);
        Py_XDECREF(dv);
        if (rc == NULL)
            goto done;
        Py_DECREF(rc);
    }
    if (track_fixes(parts, t_obj, c, &m) < 0)
        goto done;
    PyObject *constraints; /* the rows due, else Python's `constraints = []` */
    if (m.due) {
        if (set_attr(parts[E_FILTER], N_CONSTRAINTS_NS, t_obj) < 0 ||
            (constraints = PyObject_CallNoArgs(calls[C_CONSTRAINTS])) == NULL)
            goto done;
    } else if ((constraints = PyList_New(0)) == NULL) {
        goto done;
    }
    out = fuse(parts, t_obj, c, &m, constraints);
    Py_XDECREF(constraints);
    if (out != NULL && after_fuse(parts, t_obj, &m) < 0)
        Py_CLEAR(out);
done:
    Py_DECREF(t_obj);
    release(&m);
    return out;
}
