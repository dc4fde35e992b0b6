/* uwbd.fusion._core.outcomes: an epoch's row outcomes, in one call.
 *
 * After each update every row (a range, a fix axis, a ZUPT, NHC or height row) is reported
 * and counted: EpochFusion._outcomes makes its FusionReport, counts it, gives the health
 * monitor the evidence of each UWB row (HealthMonitor.uwb_outcome) and each range's
 * anchor its statistics (AnchorStats.add). This does what they do, on their own
 * attributes, in their order, with their arithmetic (the same bits), and declines
 * (returns NotImplemented, having changed nothing) for anything it does not expect, which
 * the Python code then takes: it stays the reference.
 *
 *   outcomes(parts, t_ns, keys, rows) -> [FusionReport] | NotImplemented
 * parts = (FusionReport, counters, counter names by (kind, accepted), vars(monitor),
 *          limits (range_timeout_s, window_count, max_rejected_fraction, max_mean_nis),
 *          anchor_stats, AnchorStats, gate_1), made by EpochFusion._outcome_parts;
 * keys: (kind, key) per row; rows: (innovation, variance, weight, numerical) per row.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <limits.h>
#include <stdint.h>
#include <string.h>

#include "../_tuple.h"
#include "_core.h"

enum { O_REPORT, O_COUNTERS, O_NAMES, O_MONITOR, O_LIMITS, O_STATS, O_STATS_TYPE, O_GATE,
       O_COUNT };
enum { L_TIMEOUT, L_WINDOW, L_REJECTED, L_NIS, L_COUNT };
#define MAX_ROWS 256
#define LIMIT_T (INT64_C(1) << 62)  /* times within ±this: no difference overflows */
#define EXACT (INT64_C(1) << 52)    /* differences below this are exact as doubles */

enum {
    S_RANGE, S_POSITION, S_EMPTY, S_NUMERICAL, S_GATE, S_SKIPS, S_LAST, S_OUTCOMES,
    S_REJECTED, S_NIS_SUM, S_RUN, S_SINCE, S_NUMERICAL_NS, S_REJUDGING, S_ACCEPTED,
    S_DEWEIGHTED, S_REJECTED_STAT, S_SUM_E, S_SUM_E2, S_APPEND, S_POPLEFT, S_CLEAR, S_COUNT
};
static const char *const text[S_COUNT] = {
    "range", "position", "", "numerical", "innovation_gate", "numerical_skips",
    "last_range_ns", "_outcomes", "_rejected", "_nis_sum", "_rejected_run",
    "_inconsistent_since_ns", "_numerical_ns", "_rejudging", "accepted", "deweighted",
    "rejected", "_sum_e", "_sum_e2", "append", "popleft", "clear",
};
static PyObject *str[S_COUNT];

int uwbd_outcomes_init(void)
{
    return uwbd_intern(text, str, S_COUNT);
}

static int is_kind(PyObject *kind, int which)
{
    return kind == str[which] || PyUnicode_Compare(kind, str[which]) == 0;
}

/* the monitor's evidence, read once: what uwb_outcome works on */
typedef struct {
    int has_last, rejudging, has_since;
    int64_t last, since;
    long rejected, run;
    double nis_sum;
    PyObject *deque;
    Py_ssize_t len;
} Monitor;

static int get_int64(PyObject *o, int64_t *out)
{
    if (!PyLong_CheckExact(o))
        return -1;
    int overflow = 0;
    long long x = PyLong_AsLongLongAndOverflow(o, &overflow);
    if (overflow || (x == -1 && PyErr_Occurred()) || x >= LIMIT_T || x <= -LIMIT_T) {
        PyErr_Clear();
        return -1;
    }
    *out = x;
    return 0;
}

/* -1: not as expected (decline); the monitor's fields as the Python code keeps them */
static int read_monitor(PyObject *m, Monitor *mon)
{
    PyObject *last = PyDict_GetItem(m, str[S_LAST]), *since = PyDict_GetItem(m, str[S_SINCE]);
    PyObject *rej = PyDict_GetItem(m, str[S_REJECTED]), *nis = PyDict_GetItem(m, str[S_NIS_SUM]);
    PyObject *run = PyDict_GetItem(m, str[S_RUN]), *judging = PyDict_GetItem(m, str[S_REJUDGING]);
    PyObject *deque = PyDict_GetItem(m, str[S_OUTCOMES]);
    if (!last || !since || !rej || !nis || !run || !judging || !deque)
        return -1;
    mon->has_last = last != Py_None;
    mon->has_since = since != Py_None;
    if ((mon->has_last && get_int64(last, &mon->last)) ||
        (mon->has_since && get_int64(since, &mon->since)))
        return -1;
    if (!PyLong_CheckExact(rej) || !PyLong_CheckExact(run) || !PyFloat_CheckExact(nis) ||
        !PyBool_Check(judging))
        return -1;
    mon->rejected = PyLong_AsLong(rej);
    mon->run = PyLong_AsLong(run);
    if (PyErr_Occurred()) {
        PyErr_Clear();
        return -1;
    }
    /* counts a call can add to or take from without leaving a long */
    if (mon->rejected > LONG_MAX - MAX_ROWS || mon->rejected < LONG_MIN + MAX_ROWS ||
        mon->run > LONG_MAX - MAX_ROWS || mon->run < 0)
        return -1;
    mon->nis_sum = PyFloat_AS_DOUBLE(nis);
    mon->rejudging = judging == Py_True;
    if (strcmp(Py_TYPE(deque)->tp_name, "collections.deque") != 0)
        return -1;
    mon->len = PyObject_Length(deque);
    if (mon->len < 0)
        return -1;
    mon->deque = Py_NewRef(deque); /* held: Python code may run before it is done with */
    return 0;
}

static int set_item(PyObject *d, int name, PyObject *value)
{
    if (value == NULL)
        return -1;
    int rc = PyDict_SetItem(d, str[name], value);
    Py_DECREF(value);
    return rc;
}

/* HealthMonitor.uwb_outcome and _window_inconsistent, on mon; the deque changed here */
static int uwb_outcome(Monitor *mon, const double *lim, int64_t t_ns, int accepted, double nis)
{
    if (accepted && mon->has_last && (double)(t_ns - mon->last) > lim[L_TIMEOUT] * 1e9) {
        PyObject *r = PyObject_CallMethodNoArgs(mon->deque, str[S_CLEAR]);
        if (r == NULL)
            return -1;
        Py_DECREF(r);
        mon->len = 0;
        mon->rejected = 0;
        mon->nis_sum = 0.0;
        mon->rejudging = 1;
    }
    if (accepted) {
        mon->has_last = 1;
        mon->last = t_ns;
        mon->run = 0;
    } else {
        mon->run += 1;
    }
    nis = nis < 25.0 ? nis : 25.0; /* NaN and inf too */
    PyObject *entry = Py_BuildValue("(Nd)", PyBool_FromLong(accepted), nis);
    if (entry == NULL)
        return -1;
    PyObject *r = PyObject_CallMethodOneArg(mon->deque, str[S_APPEND], entry);
    Py_DECREF(entry);
    if (r == NULL)
        return -1;
    Py_DECREF(r);
    mon->len += 1;
    mon->rejected += !accepted;
    mon->nis_sum += nis;
    long window = (long)lim[L_WINDOW];
    if (mon->len > window) {
        PyObject *old = PyObject_CallMethodNoArgs(mon->deque, str[S_POPLEFT]);
        if (old == NULL)
            return -1;
        if (!PyTuple_Check(old) || PyTuple_GET_SIZE(old) != 2) {
            Py_DECREF(old);
            PyErr_SetString(PyExc_TypeError, "HealthMonitor._outcomes: (accepted, nis) expected");
            return -1;
        }
        int old_accepted = PyObject_IsTrue(PyTuple_GET_ITEM(old, 0));
        double old_nis = PyFloat_AsDouble(PyTuple_GET_ITEM(old, 1));
        Py_DECREF(old);
        if (old_accepted < 0 || PyErr_Occurred())
            return -1;
        mon->len -= 1;
        mon->rejected -= !old_accepted;
        mon->nis_sum -= old_nis;
    }
    if (mon->rejudging && mon->len >= window)
        mon->rejudging = 0;
    int inconsistent;
    if (mon->run >= 4)
        inconsistent = 1;
    else if (mon->len < window)
        inconsistent = 0;
    else
        inconsistent = (double)mon->rejected > lim[L_REJECTED] * (double)mon->len ||
                       mon->nis_sum / (double)mon->len > lim[L_NIS];
    if (inconsistent) {
        if (!mon->has_since) {
            mon->has_since = 1;
            mon->since = t_ns;
        }
    } else {
        mon->has_since = 0;
    }
    return 0;
}

static int write_monitor(PyObject *m, const Monitor *mon)
{
    return (set_item(m, S_LAST, mon->has_last ? PyLong_FromLongLong(mon->last) : Py_NewRef(Py_None)) ||
           set_item(m, S_SINCE, mon->has_since ? PyLong_FromLongLong(mon->since) : Py_NewRef(Py_None)) ||
           set_item(m, S_REJECTED, PyLong_FromLong(mon->rejected)) ||
           set_item(m, S_RUN, PyLong_FromLong(mon->run)) ||
           set_item(m, S_NIS_SUM, PyFloat_FromDouble(mon->nis_sum)) ||
           set_item(m, S_REJUDGING, PyBool_FromLong(mon->rejudging))) ? -1 : 0;
}

/* counters[name] += 1 (a Counter: a missing name counts 0) */
static int count(PyObject *counters, PyObject *name)
{
    PyObject *old = PyDict_GetItemWithError(counters, name);
    if (old == NULL && PyErr_Occurred())
        return -1;
    PyObject *one = PyLong_FromLong(1);
    PyObject *sum = old == NULL ? Py_NewRef(one) : PyNumber_Add(old, one);
    Py_DECREF(one);
    if (sum == NULL)
        return -1;
    int rc = PyDict_SetItem(counters, name, sum);
    Py_DECREF(sum);
    return rc;
}

static int add_stat(PyObject *d, double e, double w);

/* An AnchorStats's fields as the Python code keeps them (checked before anything changes,
 * so that add_stat cannot fail half-way on them): 1 yes, 0 no, -1 an error */
static int stats_as_expected(PyObject *stats, PyObject *anchor, PyObject *type)
{
    PyObject *s = PyDict_GetItemWithError(stats, anchor);
    if (s == NULL)
        return PyErr_Occurred() ? -1 : 1; /* made new, with its defaults */
    if (Py_TYPE(s) != (PyTypeObject *)type)
        return 0; /* another object (its own add): the reference's */
    Py_INCREF(s);
    PyObject *d = PyObject_GenericGetDict(s, NULL);
    Py_DECREF(s);
    if (d == NULL) {
        PyErr_Clear();
        return 0;
    }
    int ok = 1;
    for (int name = S_ACCEPTED; name <= S_SUM_E2 && ok; name++) {
        PyObject *v = PyDict_GetItem(d, str[name]);
        ok = v != NULL && (name < S_SUM_E ? PyLong_CheckExact(v) : PyFloat_CheckExact(v));
    }
    Py_DECREF(d);
    return ok;
}

/* AnchorStats.add(e, weight) on the anchor's stats (made when it has none) */
static int anchor_add(PyObject *stats, PyObject *type, PyObject *anchor, double e, double w)
{
    PyObject *s = PyDict_GetItemWithError(stats, anchor);
    if (s == NULL) {
        if (PyErr_Occurred())
            return -1;
        s = PyObject_CallNoArgs(type);
        if (s == NULL)
            return -1;
        int rc = PyDict_SetItem(stats, anchor, s);
        Py_DECREF(s);
        if (rc < 0)
            return -1;
    }
    PyObject *d = PyObject_GenericGetDict(s, NULL); /* vars(s) */
    if (d == NULL)
        return -1;
    int rc = add_stat(d, e, w);
    Py_DECREF(d);
    return rc;
}

static int add_stat(PyObject *d, double e, double w)
{
    int which = w <= 0.0 ? S_REJECTED_STAT : S_ACCEPTED;
    PyObject *n = PyDict_GetItem(d, str[which]);
    if (n == NULL || !PyLong_CheckExact(n)) {
        PyErr_SetString(PyExc_TypeError, "AnchorStats: an int count expected");
        return -1;
    }
    PyObject *one = PyLong_FromLong(1);
    if (one == NULL)
        return -1;
    int rc = set_item(d, which, PyNumber_Add(n, one));
    Py_DECREF(one);
    if (rc < 0)
        return -1;
    if (w <= 0.0)
        return 0;
    PyObject *dw = PyDict_GetItem(d, str[S_DEWEIGHTED]), *se = PyDict_GetItem(d, str[S_SUM_E]);
    PyObject *se2 = PyDict_GetItem(d, str[S_SUM_E2]);
    if (dw == NULL || se == NULL || se2 == NULL || !PyFloat_Check(se) || !PyFloat_Check(se2)) {
        PyErr_SetString(PyExc_TypeError, "AnchorStats: its sums expected");
        return -1;
    }
    PyObject *inc = PyLong_FromLong(w < 0.5);
    if (inc == NULL)
        return -1;
    rc = set_item(d, S_DEWEIGHTED, PyNumber_Add(dw, inc));
    Py_DECREF(inc);
    if (rc < 0)
        return -1;
    /* (to the bit but for which NaN's sign survives a NaN + NaN) */
    double sum_e = PyFloat_AS_DOUBLE(se), sum_e2 = PyFloat_AS_DOUBLE(se2);
    return (set_item(d, S_SUM_E, PyFloat_FromDouble(sum_e + e)) ||
            set_item(d, S_SUM_E2, PyFloat_FromDouble(sum_e2 + e * e))) ? -1 : 0;
}

typedef struct {
    PyObject *kind, *key, *name, *anchor; /* all held: Python code runs before their use */
    double innovation, variance, weight, ratio;
    int numerical, uwb, range;
} RowIn;

/* Every row read and checked before anything changes: 1 taken, 0 declined, -1 an error */
static int read_rows(PyObject *keys, PyObject *rows, PyObject *names, PyObject *stats,
                     PyObject *stats_type, double gate_1, RowIn *in, Py_ssize_t n,
                     int *any_uwb)
{
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *k = PyList_GET_ITEM(keys, i), *r = PyList_GET_ITEM(rows, i);
        if (!PyTuple_Check(k) || PyTuple_GET_SIZE(k) != 2 || !PyTuple_Check(r) ||
            PyTuple_GET_SIZE(r) != 4)
            return 0;
        RowIn *row = &in[i];
        row->kind = Py_NewRef(PyTuple_GET_ITEM(k, 0));
        row->key = Py_NewRef(PyTuple_GET_ITEM(k, 1));
        PyObject *nu = PyTuple_GET_ITEM(r, 0), *s = PyTuple_GET_ITEM(r, 1);
        PyObject *w = PyTuple_GET_ITEM(r, 2), *num = PyTuple_GET_ITEM(r, 3);
        if (!PyUnicode_CheckExact(row->kind) || !PyUnicode_CheckExact(row->key) ||
            !PyFloat_CheckExact(nu) || !PyFloat_CheckExact(s) || !PyFloat_CheckExact(w) ||
            !PyBool_Check(num))
            return 0;
        row->innovation = PyFloat_AS_DOUBLE(nu);
        row->variance = PyFloat_AS_DOUBLE(s);
        row->weight = PyFloat_AS_DOUBLE(w);
        row->numerical = num == Py_True;
        row->range = is_kind(row->kind, S_RANGE);
        row->uwb = row->range || is_kind(row->kind, S_POSITION);
        *any_uwb |= row->uwb;
        row->ratio = NAN;
        if (row->variance > 0) {
            /* Python's innovation**2 is libm's pow (which the compiler would make x * x, not
             * always the same bits: the exponent is hidden from it); where that overflows
             * Python raises OverflowError: the reference's to raise */
            volatile double two = 2.0;
            double square = pow(row->innovation, two);
            if (isinf(square) && isfinite(row->innovation))
                return 0;
            row->ratio = square / row->variance / gate_1;
        }
        PyObject *name_key = PyTuple_Pack(2, row->kind, row->weight > 0.0 ? Py_True : Py_False);
        if (name_key == NULL)
            return -1;
        PyObject *name = PyDict_GetItemWithError(names, name_key);
        Py_DECREF(name_key);
        if (name == NULL)
            return PyErr_Occurred() ? -1 : 0; /* a kind not known: the reference names it */
        row->name = Py_NewRef(name);
        if (row->range) {
            row->anchor = PyLong_FromUnicodeObject(row->key, 10);
            if (row->anchor == NULL) {
                PyErr_Clear();
                return 0;
            }
            int ok = stats_as_expected(stats, row->anchor, stats_type);
            if (ok <= 0)
                return ok;
        }
    }
    return 1;
}

PyObject *uwbd_outcomes(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 4 || !PyTuple_Check(args[0]) || PyTuple_GET_SIZE(args[0]) != O_COUNT ||
        !PyList_Check(args[2]) || !PyList_Check(args[3])) {
        PyErr_SetString(PyExc_TypeError, "outcomes(parts, t_ns, keys, rows)");
        return NULL;
    }
    PyObject *const *parts = &PyTuple_GET_ITEM(args[0], 0);
    PyObject *report_type = parts[O_REPORT], *counters = parts[O_COUNTERS];
    PyObject *names = parts[O_NAMES], *m = parts[O_MONITOR], *stats = parts[O_STATS];
    Py_ssize_t n = PyList_GET_SIZE(args[2]);
    int64_t t_ns;
    double lim[L_COUNT], gate_1 = PyFloat_Check(parts[O_GATE]) ?
                                       PyFloat_AS_DOUBLE(parts[O_GATE]) : NAN;
    /* (a gate of 0 or less: the reference divides by it, and says so; a window of no whole
     * count, or none: the reference's arithmetic then is not this) */
    if (n != PyList_GET_SIZE(args[3]) || n > MAX_ROWS || get_int64(args[1], &t_ns) ||
        !(gate_1 > 0.0) || !PyDict_Check(counters) || !PyDict_Check(names) ||
        !PyDict_Check(m) || !PyDict_Check(stats) || !PyType_Check(report_type) ||
        !PyType_IsSubtype((PyTypeObject *)report_type, &PyTuple_Type) ||
        !PyLong_CheckExact(PyTuple_Check(parts[O_LIMITS]) && PyTuple_GET_SIZE(parts[O_LIMITS])
                           == L_COUNT ? PyTuple_GET_ITEM(parts[O_LIMITS], L_WINDOW) : Py_None) ||
        uwbd_get_vec(parts[O_LIMITS], lim, L_COUNT, "limits") < 0 || !(lim[L_WINDOW] >= 1.0) ||
        !(lim[L_WINDOW] <= 1e9)) {
        PyErr_Clear();
        Py_RETURN_NOTIMPLEMENTED;
    }
    Monitor mon = {0}; /* (every field read_monitor leaves unset is read only when set) */
    if (read_monitor(m, &mon) < 0) {
        PyErr_Clear();
        Py_RETURN_NOTIMPLEMENTED;
    }
    RowIn in[MAX_ROWS];
    memset(in, 0, sizeof(RowIn) * (size_t)n);
    int any_uwb = 0;
    PyObject *out = NULL, *reports = NULL, *t_obj = NULL;
    int taken = read_rows(args[2], args[3], names, stats, parts[O_STATS_TYPE], gate_1, in, n,
                          &any_uwb);
    if (taken == 1 && any_uwb && mon.has_last &&
        (t_ns - mon.last >= EXACT || mon.last - t_ns >= EXACT))
        taken = 0; /* a time apart beyond a double's exact integers */
    if (taken <= 0) {
        out = taken < 0 ? NULL : Py_NewRef(Py_NotImplemented);
        goto done;
    }
    /* from here on the state changes: an error (only a failed allocation can make one)
     * still leaves the monitor's fields in step with its window */
    reports = PyList_New(n);
    t_obj = PyLong_FromLongLong(t_ns);
    int failed = reports == NULL || t_obj == NULL;
    for (Py_ssize_t i = 0; i < n && !failed; i++) {
        RowIn *row = &in[i];
        int ok = row->weight > 0.0;
        PyObject *reason = ok ? str[S_EMPTY] : row->numerical ? str[S_NUMERICAL] : str[S_GATE];
        PyObject *items[8] = {Py_NewRef(t_obj), Py_NewRef(row->kind), Py_NewRef(row->key),
                              PyFloat_FromDouble(row->innovation),
                              PyFloat_FromDouble(row->variance), PyFloat_FromDouble(row->ratio),
                              PyBool_FromLong(ok), Py_NewRef(reason)};
        PyObject *report = uwbd_tuple_of((PyTypeObject *)report_type, items, 8);
        if (report == NULL) {
            failed = 1;
            break;
        }
        PyList_SET_ITEM(reports, i, report);
        if (count(counters, row->name) < 0 ||
            (row->numerical && (count(counters, str[S_SKIPS]) < 0 ||
                                set_item(m, S_NUMERICAL_NS, PyLong_FromLongLong(t_ns)) < 0)) ||
            (row->uwb && uwb_outcome(&mon, lim, t_ns, ok, row->ratio * gate_1) < 0)) {
            failed = 1;
            break;
        }
        if (row->range) {
            double e = row->variance > 0 ? row->innovation / sqrt(row->variance) : NAN;
            if (anchor_add(stats, parts[O_STATS_TYPE], row->anchor, e, row->weight) < 0) {
                failed = 1;
                break;
            }
        }
    }
    if (any_uwb) {
        PyObject *type, *value, *tb;
        PyErr_Fetch(&type, &value, &tb); /* written on failure too, the error kept */
        if (write_monitor(m, &mon) < 0)
            failed = 1;
        if (type != NULL) {
            PyErr_Clear();
            PyErr_Restore(type, value, tb);
        }
    }
    out = failed ? NULL : Py_NewRef(reports);
done:
    for (Py_ssize_t j = 0; j < n; j++) {
        Py_XDECREF(in[j].kind);
        Py_XDECREF(in[j].key);
        Py_XDECREF(in[j].name);
        Py_XDECREF(in[j].anchor);
    }
    Py_XDECREF(reports);
    Py_XDECREF(t_obj);
    Py_DECREF(mon.deque);
    return out;
}
