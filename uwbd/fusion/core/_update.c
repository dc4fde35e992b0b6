/* The scalar measurement update of docs/ekf.md §5 and its robust weights (the reference:
 * Eskf._sequential_rows and robust.RowPolicy): rows fused one at a time, each at the state
 * the rows before it left, the Joseph form with the nominal R_i for any gain. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>

#include "_core.h"

#define POLICY_TYPE "decide: a callable or a RowPolicy (uwbd/fusion/core/weights.py)"

int uwbd_get_decide(PyObject *decide, UwbdRowPolicy *pol)
{
    if (!PyTuple_Check(decide)) {
        if (PyCallable_Check(decide))
            return 0;
        PyErr_SetString(PyExc_TypeError, POLICY_TYPE);
        return -1;
    }
    if (PyTuple_GET_SIZE(decide) != POLICY_FIELDS ||
        !PyBytes_Check(PyTuple_GET_ITEM(decide, POLICY_KINDS))) {
        PyErr_SetString(PyExc_TypeError, POLICY_TYPE);
        return -1;
    }
    PyObject *kinds = PyTuple_GET_ITEM(decide, POLICY_KINDS);
    pol->kinds = PyBytes_AS_STRING(kinds);
    pol->count = PyBytes_GET_SIZE(kinds);
    pol->gate_1 = PyFloat_AsDouble(PyTuple_GET_ITEM(decide, POLICY_GATE_1));
    pol->robust = PyObject_IsTrue(PyTuple_GET_ITEM(decide, POLICY_ROBUST));
    pol->c_long = PyFloat_AsDouble(PyTuple_GET_ITEM(decide, POLICY_C_LONG));
    pol->c_short = PyFloat_AsDouble(PyTuple_GET_ITEM(decide, POLICY_C_SHORT));
    pol->fix_ok = PyObject_IsTrue(PyTuple_GET_ITEM(decide, POLICY_FIX_OK));
    if (PyErr_Occurred() || pol->robust < 0 || pol->fix_ok < 0)
        return -1;
    return 1;
}

/* RowPolicy.__call__: a position axis by its fix's 3-D gate; else the χ² gate, then, for
 * a range, the Geman–McClure weight with the NLOS side's constant. */
static double policy_weight(const UwbdRowPolicy *pol, Py_ssize_t i, double nu, double s)
{
    char kind = pol->kinds[i];
    if (kind == POSITION_ROW)
        return pol->fix_ok ? 1.0 : 0.0;
    double e2 = nu * nu / s;
    if (e2 > pol->gate_1)
        return 0.0;
    if (kind != RANGE_ROW || !pol->robust)
        return 1.0;
    double e = nu / sqrt(s);
    double c = e > 0 ? pol->c_long : pol->c_short;
    double c2 = c * c;
    double w = c2 / (c2 + e * e);
    return w * w;
}

/* u = P h (P n×n). */
static void times(const double *P, const double *h, Py_ssize_t n, double *u)
{
    for (Py_ssize_t a = 0; a < n; a++) {
        double s = 0.0;
        for (Py_ssize_t b = 0; b < n; b++)
            s += P[a * n + b] * h[b];
        u[a] = s;
    }
}

/* One row fused with weight w > 0 (u = P h, S = h u + r, innovation ν): k = u / (S +
 * r (1/w − 1)), zero on [c0, c1); x += k ν; P ← P − M − Mᵀ with M = k (u − S k / 2)ᵀ. */
static void fuse_row(double *P, double *x, Py_ssize_t n, const double *u, double *k,
                     double *g, double nu, double s, double r, double w, Py_ssize_t c0,
                     Py_ssize_t c1)
{
    double denom = s + r * (1.0 / w - 1.0);
    for (Py_ssize_t a = 0; a < n; a++)
        k[a] = (a >= c0 && a < c1) ? 0.0 : u[a] / denom;
    for (Py_ssize_t a = 0; a < n; a++)
        x[a] += k[a] * nu;
    double half_s = 0.5 * s;
    for (Py_ssize_t a = 0; a < n; a++)
        g[a] = u[a] - half_s * k[a];
    for (Py_ssize_t a = 0; a < n; a++)
        for (Py_ssize_t b = 0; b < n; b++)
            P[a * n + b] = (P[a * n + b] - k[a] * g[b]) - k[b] * g[a];
}

/* For each row: u = P h, S = h u + R_i, ν = y_i − h dx; the weight w from the policy (or
 * `decide(i, ν, S)`); k = u / (S + R_i (1/w − 1)), zero on [c0, c1) (considered states);
 * dx += k ν; P ← P − M − Mᵀ with M = k (u − S k / 2)ᵀ. Each row's weight into weights
 * (unless NULL; 0 where the row was not fused). */
PyObject *uwbd_scalar_rows(double *P, double *dx, Py_ssize_t n, const double *H,
                           const double *y, const double *Rv, Py_ssize_t m, PyObject *decide,
                           const UwbdRowPolicy *pol, Py_ssize_t c0, Py_ssize_t c1,
                           double *work, int *fused, double *weights)
{
    *fused = 0;
    if (pol != NULL && pol->count != m) {
        PyErr_SetString(PyExc_ValueError, "decide: one kind per row");
        return NULL;
    }
    PyObject *rows = PyList_New(m);
    if (rows == NULL)
        return NULL;
    double *u = work, *k = work + n, *g = work + 2 * n;
    for (Py_ssize_t i = 0; i < m; i++) {
        const double *h = H + i * n;
        times(P, h, n, u);
        double r = Rv[i];
        double hu = 0.0, hdx = 0.0;
        for (Py_ssize_t a = 0; a < n; a++) {
            hu += h[a] * u[a];
            hdx += h[a] * dx[a];
        }
        double s = hu + r;
        double nu = y[i] - hdx;
        double weight = 0.0;
        int numerical = !(isfinite(s) && isfinite(nu)) || s < r * (1 - 1e-9);
        if (!numerical && pol != NULL) {
            weight = policy_weight(pol, i, nu, s);
        } else if (!numerical) {
            PyObject *res = PyObject_CallFunction(decide, "ndd", i, nu, s);
            if (res == NULL) {
                Py_CLEAR(rows);
                break;
            }
            weight = PyFloat_AsDouble(res);
            Py_DECREF(res);
            if (weight == -1.0 && PyErr_Occurred()) {
                Py_CLEAR(rows);
                break;
            }
        }
        PyObject *row = Py_BuildValue("(dddO)", nu, s, weight,
                                      numerical ? Py_True : Py_False);
        if (row == NULL) {
            Py_CLEAR(rows);
            break;
        }
        PyList_SET_ITEM(rows, i, row);
        if (numerical || !(weight > 0.0)) { /* 0, negative or NaN: not fused */
            if (weights != NULL)
                weights[i] = 0.0;
            continue;
        }
        if (weights != NULL)
            weights[i] = weight;
        *fused = 1;
        fuse_row(P, dx, n, u, k, g, nu, s, r, weight, c0, c1);
    }
    return rows;
}

/* The rows on sub-filter k (see _core.h): ν = y_i − h e, S = h P_k h + R_i, the main
 * filter's weight, the same gain and Joseph form as above; a row whose S is not finite or
 * below R_i is skipped here alone. */
void uwbd_bank_rows(double *P, double *e, Py_ssize_t n, const double *H, const double *y,
                    const double *Rv, Py_ssize_t m, const double *weights,
                    const long long *row_anchor, long long left_out, Py_ssize_t c0,
                    Py_ssize_t c1, double *work)
{
    double *u = work, *k = work + n, *g = work + 2 * n;
    for (Py_ssize_t i = 0; i < m; i++) {
        double weight = weights[i];
        if (!(weight > 0.0) || row_anchor[i] == left_out)
            continue;
        const double *h = H + i * n;
        times(P, h, n, u);
        double r = Rv[i], hu = 0.0, he = 0.0;
        for (Py_ssize_t a = 0; a < n; a++) {
            hu += h[a] * u[a];
            he += h[a] * e[a];
        }
        double s = hu + r, nu = y[i] - he;
        if (!(isfinite(s) && isfinite(nu)) || s < r * (1 - 1e-9))
            continue;
        fuse_row(P, e, n, u, k, g, nu, s, r, weight, c0, c1);
    }
}
