/* uwbd.fusion._core: the error-state EKF's per-sample and per-epoch algebra in C, and the
 * Gauss–Newton multilateration of the UWB-only fixes.
 *
 * The reference is the pure-Python code in uwbd/fusion/eskf.py (docs/ekf.md) and
 * uwbd/fusion/lsq.py; every
 * function here is a line-by-line translation of one there, named alike, and the tests
 * compare the two (tests/test_core.py). Built by the package's own build (setup.py) with
 * -ffp-contract=off, so that `a * b + c` rounds as Python rounds it; predict() is then
 * the same to the bit. Matrices arrive as numpy arrays through the buffer protocol
 * (C-contiguous float64): no numpy headers are needed to build.
 *
 * UWBD_PURE_PYTHON=1 in the environment makes uwbd ignore this module.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>

#include "_core.h"


/* -- helpers ---------------------------------------------------------------------------- */

/* A C-contiguous float64 buffer of `count` doubles (count < 0: any size). */
static int get_doubles(PyObject *obj, Py_buffer *view, Py_ssize_t count, int writable,
                       const char *what)
{
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, view, flags) < 0)
        return -1;
    if (view->itemsize != 8 || view->format == NULL || strcmp(view->format, "d") != 0) {
        PyErr_Format(PyExc_TypeError, "%s: a float64 array is needed", what);
        PyBuffer_Release(view);
        return -1;
    }
    if (count >= 0 && view->len != count * 8) {
        PyErr_Format(PyExc_ValueError, "%s: %zd numbers expected, got %zd", what, count,
                     view->len / 8);
        PyBuffer_Release(view);
        return -1;
    }
    return 0;
}

/* Three (or four) floats out of a list or tuple of floats. */
int uwbd_get_vec(PyObject *seq, double *out, Py_ssize_t n, const char *what)
{
    PyObject *fast = PySequence_Fast(seq, what);
    if (fast == NULL)
        return -1;
    if (PySequence_Fast_GET_SIZE(fast) != n) {
        PyErr_Format(PyExc_ValueError, "%s: %zd numbers expected", what, n);
        Py_DECREF(fast);
        return -1;
    }
    PyObject **items = PySequence_Fast_ITEMS(fast);
    for (Py_ssize_t i = 0; i < n; i++) {
        out[i] = PyFloat_AsDouble(items[i]);
        if (out[i] == -1.0 && PyErr_Occurred()) {
            Py_DECREF(fast);
            return -1;
        }
    }
    Py_DECREF(fast);
    return 0;
}

/* Store doubles back into an existing list, item by item (the list is mutated in place,
 * as the Python code's `p[0] += ...` does). */
int uwbd_set_list(PyObject *list, const double *v, Py_ssize_t n)
{
    if (!PyList_Check(list) || PyList_GET_SIZE(list) != n) {
        PyErr_SetString(PyExc_TypeError, "a list of the state's length is needed");
        return -1;
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *f = PyFloat_FromDouble(v[i]);
        if (f == NULL)
            return -1;
        PyList_SetItem(list, i, f); /* steals f, drops the old item */
    }
    return 0;
}

/* A new list (as_list) or tuple of n floats; NULL with an error set. */
PyObject *uwbd_floats(const double *v, Py_ssize_t n, int as_list)
{
    PyObject *out = as_list ? PyList_New(n) : PyTuple_New(n);
    for (Py_ssize_t i = 0; out != NULL && i < n; i++) {
        PyObject *f = PyFloat_FromDouble(v[i]);
        if (f == NULL)
            Py_CLEAR(out);
        else if (as_list)
            PyList_SET_ITEM(out, i, f);
        else
            PyTuple_SET_ITEM(out, i, f);
    }
    return out;
}

/* n floats out of a list (or, unless list_only, a tuple) of exactly n Python floats: 1
 * (out filled), else 0 (not so: the callers decline). */
int uwbd_floats_of(PyObject *seq, double *out, Py_ssize_t n, int list_only)
{
    PyObject **items;
    if (PyList_CheckExact(seq) && PyList_GET_SIZE(seq) == n)
        items = ((PyListObject *)seq)->ob_item;
    else if (!list_only && PyTuple_CheckExact(seq) && PyTuple_GET_SIZE(seq) == n)
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

/* The first n numbers of a tuple as doubles (a step's parts): 0, or -1 with an error set. */
int uwbd_doubles_of(PyObject *tuple, double *out, Py_ssize_t n)
{
    for (Py_ssize_t i = 0; i < n; i++)
        if ((out[i] = PyFloat_AsDouble(PyTuple_GET_ITEM(tuple, i))) == -1.0 && PyErr_Occurred())
            return -1;
    return 0;
}

/* Each of the n names interned (the namespaces are read by these keys): 0, or -1. */
int uwbd_intern(const char *const *text, PyObject **out, int n)
{
    for (int i = 0; i < n; i++)
        if ((out[i] = PyUnicode_InternFromString(text[i])) == NULL)
            return -1;
    return 0;
}

/* q ⊗ Exp(θ), normalised: eskf._turned */
static void turned(const double q[4], double tx, double ty, double tz, double out[4])
{
    double angle = sqrt(tx * tx + ty * ty + tz * tz);
    double dw, s;
    if (angle < 1e-9) {
        dw = 1.0;
        s = 0.5;
    } else {
        dw = cos(0.5 * angle);
        s = sin(0.5 * angle) / angle;
    }
    double dx = s * tx, dy = s * ty, dz = s * tz;
    double qw = q[0], qx = q[1], qy = q[2], qz = q[3];
    double nw = qw * dw - qx * dx - qy * dy - qz * dz;
    double nx = qw * dx + qx * dw + qy * dz - qz * dy;
    double ny = qw * dy - qx * dz + qy * dw + qz * dx;
    double nz = qw * dz + qx * dy - qy * dx + qz * dw;
    double norm = sqrt(nw * nw + nx * nx + ny * ny + nz * nz);
    out[0] = nw / norm;
    out[1] = nx / norm;
    out[2] = ny / norm;
    out[3] = nz / norm;
}

static void quat_to_matrix(const double q[4], double R[3][3])
{
    double w = q[0], x = q[1], y = q[2], z = q[3];
    R[0][0] = 1 - 2 * (y * y + z * z);
    R[0][1] = 2 * (x * y - w * z);
    R[0][2] = 2 * (x * z + w * y);
    R[1][0] = 2 * (x * y + w * z);
    R[1][1] = 1 - 2 * (x * x + z * z);
    R[1][2] = 2 * (y * z - w * x);
    R[2][0] = 2 * (x * z - w * y);
    R[2][1] = 2 * (y * z + w * x);
    R[2][2] = 1 - 2 * (x * x + y * y);
}

/* -- predict: every IMU sample ---------------------------------------------------------- */

/* Eskf.predict's arithmetic, step by step: p, v, sum_fn, sum_w in place, the new q in qn. */
void uwbd_predict_step(double p[3], double v[3], const double q[4], const double bg[3],
                       const double ba[3], double sfn[3], double sw[3], const double acc[3],
                       const double gyro[3], double dt, double g, double qn[4])
{
    double wx = (gyro[0] - bg[0]) * dt, wy = (gyro[1] - bg[1]) * dt, wz = (gyro[2] - bg[2]) * dt;
    double fx = acc[0] - ba[0], fy = acc[1] - ba[1], fz = acc[2] - ba[2];
    double qw = q[0], qx = q[1], qy = q[2], qz = q[3];
    double ax = (1 - 2 * (qy * qy + qz * qz)) * fx + 2 * (qx * qy - qw * qz) * fy
        + 2 * (qx * qz + qw * qy) * fz;
    double ay = 2 * (qx * qy + qw * qz) * fx + (1 - 2 * (qx * qx + qz * qz)) * fy
        + 2 * (qy * qz - qw * qx) * fz;
    double az = 2 * (qx * qz - qw * qy) * fx + 2 * (qy * qz + qw * qx) * fy
        + (1 - 2 * (qx * qx + qy * qy)) * fz;
    sfn[0] += ax * dt;
    sfn[1] += ay * dt;
    sfn[2] += az * dt;
    sw[0] += wx;
    sw[1] += wy;
    sw[2] += wz;
    az -= g;
    p[0] += (v[0] + 0.5 * ax * dt) * dt;
    p[1] += (v[1] + 0.5 * ay * dt) * dt;
    p[2] += (v[2] + 0.5 * az * dt) * dt;
    v[0] += ax * dt;
    v[1] += ay * dt;
    v[2] += az * dt;
    turned(q, wx, wy, wz, qn);
}

/* the Eskf's attributes the nominal state is read from and written to */
static const char *const nominal_text[9] = {"p", "v", "q", "b_g", "b_a", "_sum_fn", "_sum_w",
                                            "gravity_mps2", "_T"};
static PyObject *keys[9];
/* and those Eskf.propagate reads and writes (uwbd_propagate) */
enum { G_CORE, G_MARKOV, G_T, G_DV, G_SUM_FN, G_SUM_W, G_P, G_PHI, G_KEEP, G_Q, G_Q_RATE,
       G_PROPAGATED, G_COUNT };
static const char *const propagate_text[G_COUNT] = {
    "_core", "_markov", "_T", "_dv_epoch", "_sum_fn", "_sum_w", "P", "_Phi_epoch",
    "keep_transition", "q", "_q_rate", "_epoch_propagated"};
static PyObject *propagate_keys[G_COUNT];

int uwbd_nominal_init(void)
{
    return uwbd_intern(nominal_text, keys, 9) < 0 ? -1
           : uwbd_intern(propagate_text, propagate_keys, G_COUNT);
}

int uwbd_nominal_read(PyObject *ns, UwbdNominal *s)
{
    const int sizes[7] = {3, 3, 4, 3, 3, 3, 3};
    for (int i = 0; i < 7; i++) {
        PyObject *v = PyDict_GetItemWithError(ns, keys[i]);
        if (v == NULL) {
            if (!PyErr_Occurred())
                PyErr_Format(PyExc_AttributeError, "the Eskf has no attribute %U", keys[i]);
            return -1;
        }
        if (!uwbd_floats_of(v, s->st[i], sizes[i], i != 2))
            return 0;
        s->lists[i] = Py_NewRef(v);
    }
    PyObject *g = PyDict_GetItemWithError(ns, keys[7]);
    PyObject *interval = g == NULL ? NULL : PyDict_GetItemWithError(ns, keys[8]);
    if (interval == NULL) {
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_AttributeError, "the Eskf has no gravity_mps2 or _T");
        return -1;
    }
    if (!PyFloat_CheckExact(g) || !PyFloat_CheckExact(interval))
        return 0;
    s->gravity = PyFloat_AS_DOUBLE(g);
    s->interval = PyFloat_AS_DOUBLE(interval);
    return 1;
}

int uwbd_nominal_predict(UwbdNominal *s, PyObject *ns, const double acc[3],
                         const double gyro[3], double dt, double *interval)
{
    double qn[4];
    uwbd_predict_step(s->st[0], s->st[1], s->st[2], s->st[3], s->st[4], s->st[5], s->st[6],
                      acc, gyro, dt, s->gravity, qn);
    if (uwbd_set_list(s->lists[0], s->st[0], 3) || uwbd_set_list(s->lists[1], s->st[1], 3) ||
        uwbd_set_list(s->lists[5], s->st[5], 3) || uwbd_set_list(s->lists[6], s->st[6], 3))
        return -1;
    PyObject *q = uwbd_floats(qn, 4, 1);
    int failed = q == NULL || PyDict_SetItem(ns, keys[2], q) < 0;
    Py_XDECREF(q);
    *interval = s->interval + dt;
    PyObject *T = failed ? NULL : PyFloat_FromDouble(*interval);
    failed = T == NULL || PyDict_SetItem(ns, keys[8], T) < 0;
    Py_XDECREF(T);
    return failed ? -1 : 0;
}

void uwbd_nominal_release(UwbdNominal *s)
{
    for (int i = 0; i < 7; i++)
        Py_CLEAR(s->lists[i]);
}

/* predict(p, v, q, b_g, b_a, sum_fn, sum_w, acc_b, gyro_b, dt, gravity) -> new q (list)
 * p, v, sum_fn, sum_w are updated in place; Eskf.predict in eskf.py, step by step. */
static PyObject *core_predict(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 11) {
        PyErr_SetString(PyExc_TypeError, "predict takes 11 arguments");
        return NULL;
    }
    double p[3], v[3], q[4], bg[3], ba[3], sfn[3], sw[3], acc[3], gyro[3];
    if (uwbd_get_vec(args[0], p, 3, "p") || uwbd_get_vec(args[1], v, 3, "v") ||
        uwbd_get_vec(args[2], q, 4, "q") || uwbd_get_vec(args[3], bg, 3, "b_g") ||
        uwbd_get_vec(args[4], ba, 3, "b_a") || uwbd_get_vec(args[5], sfn, 3, "sum_fn") ||
        uwbd_get_vec(args[6], sw, 3, "sum_w") || uwbd_get_vec(args[7], acc, 3, "acc_b") ||
        uwbd_get_vec(args[8], gyro, 3, "gyro_b"))
        return NULL;
    double dt = PyFloat_AsDouble(args[9]);
    if (dt == -1.0 && PyErr_Occurred())
        return NULL;
    double g = PyFloat_AsDouble(args[10]);
    if (g == -1.0 && PyErr_Occurred())
        return NULL;
    /* every target a list of 3 before anything is written */
    const int targets[4] = {0, 1, 5, 6};
    for (int i = 0; i < 4; i++)
        if (!PyList_Check(args[targets[i]]) || PyList_GET_SIZE(args[targets[i]]) != 3) {
            PyErr_SetString(PyExc_TypeError, "p, v, sum_fn and sum_w must be lists of 3");
            return NULL;
        }
    double qn[4];
    uwbd_predict_step(p, v, q, bg, ba, sfn, sw, acc, gyro, dt, g, qn);
    if (uwbd_set_list(args[0], p, 3) || uwbd_set_list(args[1], v, 3) ||
        uwbd_set_list(args[5], sfn, 3) || uwbd_set_list(args[6], sw, 3))
        return NULL;
    return Py_BuildValue("[dddd]", qn[0], qn[1], qn[2], qn[3]);
}

/* -- propagate: once per update interval ------------------------------------------------ */

/* The columns of each row of M (15×15) that are not zero, in order, and how many. */
static void nonzeros(const double M[N_CORE][N_CORE], int nz[N_CORE][N_CORE], int count[N_CORE])
{
    for (int i = 0; i < N_CORE; i++) {
        count[i] = 0;
        for (int k = 0; k < N_CORE; k++)
            if (M[i][k] != 0.0)
                nz[i][count[i]++] = k;
    }
}

/* propagate_core(P, Phi_epoch, q, sum_fn, sum_w, T, q_rate[, symmetrise])
 * The core part of Eskf.propagate, in place on P (n×n) and Phi_epoch (15×15):
 * F from the mean specific force and rate over T, Φ = I + A + A²/2 with A = F T,
 * Φ_epoch ← Φ Φ_epoch (Phi_epoch None: not kept), P ← Φ P Φᵀ on the core rows and
 * columns, P += diag(q_rate) T;
 * with symmetrise (no Gauss–Markov step to come between), P ← (P + Pᵀ)/2 too, as numpy's
 * 0.5 * (P + P.T) makes it (the same bits: a sum of two does not depend on their order). */
static PyObject *core_propagate(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 7 && nargs != 8) {
        PyErr_SetString(PyExc_TypeError, "propagate_core takes 7 or 8 arguments");
        return NULL;
    }
    int symmetrise = nargs == 8 ? PyObject_IsTrue(args[7]) : 0;
    if (symmetrise < 0)
        return NULL;
    double q[4], sfn[3], sw[3];
    if (uwbd_get_vec(args[2], q, 4, "q") || uwbd_get_vec(args[3], sfn, 3, "sum_fn") ||
        uwbd_get_vec(args[4], sw, 3, "sum_w"))
        return NULL;
    double T = PyFloat_AsDouble(args[5]);
    if (PyErr_Occurred())
        return NULL;
    Py_buffer Pb, Eb, Qb;
    if (get_doubles(args[0], &Pb, -1, 1, "P") < 0)
        return NULL;
    Py_ssize_t n = (Py_ssize_t)sqrt((double)(Pb.len / 8));
    if (n * n * 8 != Pb.len || n < N_CORE) {
        PyBuffer_Release(&Pb);
        PyErr_SetString(PyExc_ValueError, "P must be square, at least 15x15");
        return NULL;
    }
    int keep = args[1] != Py_None; /* Φ_epoch kept (for the smoother), else None */
    if (keep && get_doubles(args[1], &Eb, N_CORE * N_CORE, 1, "Phi_epoch") < 0) {
        PyBuffer_Release(&Pb);
        return NULL;
    }
    if (get_doubles(args[6], &Qb, n, 0, "q_rate") < 0) {
        PyBuffer_Release(&Pb);
        if (keep)
            PyBuffer_Release(&Eb);
        return NULL;
    }
    double *P = (double *)Pb.buf, *E = keep ? (double *)Eb.buf : NULL;
    const double *qr = (const double *)Qb.buf;
    double R[3][3];
    quat_to_matrix(q, R);
    double f[3] = {sfn[0] / T, sfn[1] / T, sfn[2] / T};
    double w[3] = {sw[0] / T, sw[1] / T, sw[2] / T};
    /* A = F T: P_V = I, V_TH = -[f]x R, V_BA = -R, TH_TH = -[w]x, TH_BG = -I */
    double A[N_CORE][N_CORE];
    memset(A, 0, sizeof A);
    double sk[3][3] = {{0, -f[2], f[1]}, {f[2], 0, -f[0]}, {-f[1], f[0], 0}};
    for (int i = 0; i < 3; i++) {
        A[i][3 + i] = T;
        A[6 + i][9 + i] = -T;
        for (int j = 0; j < 3; j++) {
            double s = 0.0;
            for (int k = 0; k < 3; k++)
                s += sk[i][k] * R[k][j];
            A[3 + i][6 + j] = -s * T;
            A[3 + i][12 + j] = -R[i][j] * T;
        }
    }
    double sw_[3][3] = {{0, -w[2], w[1]}, {w[2], 0, -w[0]}, {-w[1], w[0], 0}};
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            A[6 + i][6 + j] = -sw_[i][j] * T;
    /* A and Φ are about half zeros: each product runs over the nonzero terms of a row only,
     * in the same order (a ±0 term leaves a finite sum as it is: the same numbers) */
    int nz[N_CORE][N_CORE], count[N_CORE];
    nonzeros(A, nz, count);
    double Phi[N_CORE][N_CORE];
    for (int i = 0; i < N_CORE; i++)
        for (int j = 0; j < N_CORE; j++) {
            double s = 0.0;
            for (int c = 0; c < count[i]; c++)
                s += A[i][nz[i][c]] * A[nz[i][c]][j];
            Phi[i][j] = (i == j ? 1.0 : 0.0) + A[i][j] + 0.5 * s;
        }
    nonzeros(Phi, nz, count);
    /* (the work space first: a failure leaves every argument as it was) */
    double *rows = PyMem_Malloc(sizeof(double) * N_CORE * n);
    if (rows == NULL) {
        PyBuffer_Release(&Pb);
        if (keep)
            PyBuffer_Release(&Eb);
        PyBuffer_Release(&Qb);
        return PyErr_NoMemory();
    }
    /* Φ_epoch ← Φ Φ_epoch */
    double tmp[N_CORE * N_CORE];
    for (int i = 0; keep && i < N_CORE; i++)
        for (int j = 0; j < N_CORE; j++) {
            double s = 0.0;
            for (int c = 0; c < count[i]; c++)
                s += Phi[i][nz[i][c]] * E[nz[i][c] * N_CORE + j];
            tmp[i * N_CORE + j] = s;
        }
    if (keep)
        memcpy(E, tmp, sizeof tmp);
    /* P[:15, :] ← Φ P[:15, :] (15×n), then P[:, :15] ← P[:, :15] Φᵀ (n×15) */
    for (int i = 0; i < N_CORE; i++) { /* each sum in the order above, along a row at once */
        double *restrict out = rows + i * n;
        for (Py_ssize_t j = 0; j < n; j++)
            out[j] = 0.0;
        for (int c = 0; c < count[i]; c++) {
            const double f = Phi[i][nz[i][c]], *restrict in = P + nz[i][c] * n;
            for (Py_ssize_t j = 0; j < n; j++)
                out[j] += f * in[j];
        }
    }
    memcpy(P, rows, sizeof(double) * N_CORE * n);
    /* then P[:, :15] Φᵀ: column j of it (in rows, as row j) summed in the same order */
    for (int j = 0; j < N_CORE; j++) {
        double *restrict out = rows + j * n;
        for (Py_ssize_t i = 0; i < n; i++)
            out[i] = 0.0;
        for (int c = 0; c < count[j]; c++) {
            const int k = nz[j][c];
            const double f = Phi[j][k];
            for (Py_ssize_t i = 0; i < n; i++)
                out[i] += P[i * n + k] * f;
        }
    }
    for (Py_ssize_t i = 0; i < n; i++)
        for (int j = 0; j < N_CORE; j++)
            P[i * n + j] = rows[j * n + i];
    PyMem_Free(rows);
    for (Py_ssize_t i = 0; i < n; i++)
        P[i * n + i] += qr[i] * T;
    if (symmetrise)
        for (Py_ssize_t i = 0; i < n; i++)
            for (Py_ssize_t j = i; j < n; j++)
                P[i * n + j] = P[j * n + i] = 0.5 * (P[i * n + j] + P[j * n + i]);
    PyBuffer_Release(&Pb);
    if (keep)
        PyBuffer_Release(&Eb);
    PyBuffer_Release(&Qb);
    Py_RETURN_NONE;
}

/* Eskf.propagate without its Python call, on vars(ekf) (propagate_keys) */
int uwbd_propagate(PyObject *ns)
{
    PyObject *v[G_COUNT]; /* held: a __bool__ or a collection below may run Python code */
    for (int i = 0; i < G_COUNT; i++) {
        if ((v[i] = PyDict_GetItemWithError(ns, propagate_keys[i])) == NULL) {
            for (int j = 0; j < i; j++)
                Py_DECREF(v[j]);
            return PyErr_Occurred() ? -1 : 0;
        }
        Py_INCREF(v[i]);
    }
    int done = 0;
    PyObject *T0 = NULL, *fn0 = NULL, *w0 = NULL;
    double T = 0.0, dv[3], sum_fn[3], zero[3] = {0.0, 0.0, 0.0};
    /* the method's `P = ascontiguousarray(P)` keeps a contiguous ndarray as it is (a subclass
     * it would make a plain one: declined) */
    if (v[G_CORE] == Py_None || !PyFloat_CheckExact(v[G_T]) ||
        strcmp(Py_TYPE(v[G_P])->tp_name, "numpy.ndarray") != 0)
        goto out;
    T = PyFloat_AS_DOUBLE(v[G_T]);
    if (T <= 0.0) { /* (as the method: nothing to propagate) */
        done = 1;
        goto out;
    }
    /* a Gauss–Markov step follows, and the symmetrising after it: the method's; so is
     * anything whose truth or length raises (the method raises it where it raises it) */
    Py_ssize_t markov = PyObject_Length(v[G_MARKOV]);
    int keep = markov == 0 ? PyObject_IsTrue(v[G_KEEP]) : -1;
    if (markov != 0 || keep < 0 || !uwbd_floats_of(v[G_DV], dv, 3, 1) ||
        !uwbd_floats_of(v[G_SUM_FN], sum_fn, 3, 1)) {
        PyErr_Clear();
        goto out;
    }
    /* what the writes after the propagation need, made first: nothing can fail after it */
    T0 = PyFloat_FromDouble(0.0);
    fn0 = uwbd_floats(zero, 3, 1);
    w0 = uwbd_floats(zero, 3, 1);
    if (T0 == NULL || fn0 == NULL || w0 == NULL) {
        done = -1;
        goto out;
    }
    /* core_propagate checks its arguments before it changes anything: one not as it expects
     * is declined, and the method (which raises what it raises) takes it */
    PyObject *args[8] = {v[G_P], keep ? v[G_PHI] : Py_None, v[G_Q], v[G_SUM_FN], v[G_SUM_W],
                         v[G_T], v[G_Q_RATE], Py_True};
    PyObject *rc = core_propagate(NULL, args, 8);
    if (rc == NULL) {
        if (PyErr_ExceptionMatches(PyExc_MemoryError)) {
            done = -1;
            goto out;
        }
        PyErr_Clear();
        goto out;
    }
    Py_DECREF(rc);
    for (int i = 0; i < 3; i++)
        dv[i] += sum_fn[i];
    done = uwbd_set_list(v[G_DV], dv, 3) < 0 ||
                   PyDict_SetItem(ns, propagate_keys[G_PROPAGATED], Py_True) < 0 ||
                   PyDict_SetItem(ns, propagate_keys[G_T], T0) < 0 || /* _reset_interval */
                   PyDict_SetItem(ns, propagate_keys[G_SUM_FN], fn0) < 0 ||
                   PyDict_SetItem(ns, propagate_keys[G_SUM_W], w0) < 0
               ? -1 : 1;
out:
    Py_XDECREF(T0);
    Py_XDECREF(fn0);
    Py_XDECREF(w0);
    for (int i = 0; i < G_COUNT; i++)
        Py_DECREF(v[i]);
    return done;
}

/* -- sequential scalar update: every UWB epoch ------------------------------------------ */

/* The weight of one row (Filter._fuse's decide, robust.RobustPolicy.weight) when the
 * caller hands the policy as a tuple (gating.RowPolicy): kinds[i] 'p' a position axis
 * (fix_ok decides), 'r' a range (χ² gate, then the Geman–McClure weight), any other a
 * gated pseudo-measurement of weight 1. */
typedef struct {
    const char *kinds;
    Py_ssize_t count;
    double gate_1, c_long, c_short;
    int robust, fix_ok;
} RowPolicy;

static int get_policy(PyObject *obj, RowPolicy *pol)
{
    if (!PyTuple_Check(obj) || PyTuple_GET_SIZE(obj) != 6 ||
        !PyBytes_Check(PyTuple_GET_ITEM(obj, 0))) {
        PyErr_SetString(PyExc_TypeError,
                        "decide: a callable or (kinds, gate_1, robust, c_long, c_short, fix_ok)");
        return -1;
    }
    PyObject *kinds = PyTuple_GET_ITEM(obj, 0);
    pol->kinds = PyBytes_AS_STRING(kinds);
    pol->count = PyBytes_GET_SIZE(kinds);
    pol->gate_1 = PyFloat_AsDouble(PyTuple_GET_ITEM(obj, 1));
    pol->robust = PyObject_IsTrue(PyTuple_GET_ITEM(obj, 2));
    pol->c_long = PyFloat_AsDouble(PyTuple_GET_ITEM(obj, 3));
    pol->c_short = PyFloat_AsDouble(PyTuple_GET_ITEM(obj, 4));
    pol->fix_ok = PyObject_IsTrue(PyTuple_GET_ITEM(obj, 5));
    if (PyErr_Occurred() || pol->robust < 0 || pol->fix_ok < 0)
        return -1;
    return 0;
}

static double policy_weight(const RowPolicy *pol, Py_ssize_t i, double nu, double s)
{
    char kind = pol->kinds[i];
    if (kind == 'p')
        return pol->fix_ok ? 1.0 : 0.0;
    double e2 = nu * nu / s;
    if (e2 > pol->gate_1)
        return 0.0;
    if (kind != 'r' || !pol->robust)
        return 1.0;
    double e = nu / sqrt(s);
    double c = e > 0 ? pol->c_long : pol->c_short;
    double c2 = c * c;
    double w = c2 / (c2 + e * e);
    return w * w;
}

/* The rows of Eskf.sequential_update, in the O(n²)-per-row form, in place on P (n×n) and
 * dx (n): for each row, u = P h, S = h u + R_i, ν = y_i − h dx; the weight w from
 * `decide(i, ν, S)` (a callable) or the policy above; k = u / (S + R_i (1/w − 1)), zero on
 * [c0, c1) (considered states); dx += k ν; P ← P − M − Mᵀ with M = k (u − S k / 2)ᵀ.
 * Returns the list of (ν, S, w, numerical) and in *fused whether any weight was > 0. */
static PyObject *scalar_rows(double *P, double *dx, Py_ssize_t n, const double *H,
                             const double *y, const double *Rv, Py_ssize_t m,
                             PyObject *decide, const RowPolicy *pol, Py_ssize_t c0,
                             Py_ssize_t c1, int *fused)
{
    *fused = 0;
    PyObject *rows = PyList_New(m);
    double *u = PyMem_Malloc(sizeof(double) * 3 * n);
    if (rows == NULL || u == NULL) {
        Py_XDECREF(rows);
        PyMem_Free(u);
        return PyErr_NoMemory();
    }
    double *k = u + n, *g = u + 2 * n;
    for (Py_ssize_t i = 0; i < m; i++) {
        const double *h = H + i * n;
        for (Py_ssize_t a = 0; a < n; a++) {
            double s = 0.0;
            for (Py_ssize_t b = 0; b < n; b++)
                s += P[a * n + b] * h[b];
            u[a] = s;
        }
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
        if (numerical || !(weight > 0.0)) /* 0, negative or NaN: not fused */
            continue;
        *fused = 1;
        double denom = s + r * (1.0 / weight - 1.0);
        for (Py_ssize_t a = 0; a < n; a++)
            k[a] = (a >= c0 && a < c1) ? 0.0 : u[a] / denom;
        for (Py_ssize_t a = 0; a < n; a++)
            dx[a] += k[a] * nu;
        /* M = k gᵀ with g = u − S k/2; P ← (P − M) − Mᵀ, rounded as numpy rounds it */
        double half_s = 0.5 * s;
        for (Py_ssize_t a = 0; a < n; a++)
            g[a] = u[a] - half_s * k[a];
        for (Py_ssize_t a = 0; a < n; a++)
            for (Py_ssize_t b = 0; b < n; b++)
                P[a * n + b] = (P[a * n + b] - k[a] * g[b]) - k[b] * g[a];
    }
    PyMem_Free(u);
    return rows;
}

/* P ← T P Tᵀ with T = I but for its attitude block G: only the attitude rows and columns
 * change (rows P[θ, :] ← G P[θ, :], then columns P[:, θ] ← P[:, θ] Gᵀ). */
static void transform_attitude(double *P, Py_ssize_t n, const double G[3][3])
{
    const Py_ssize_t t0 = 6;
    for (Py_ssize_t b = 0; b < n; b++) {
        double c0 = P[t0 * n + b], c1 = P[(t0 + 1) * n + b], c2 = P[(t0 + 2) * n + b];
        for (int i = 0; i < 3; i++)
            P[(t0 + i) * n + b] = G[i][0] * c0 + G[i][1] * c1 + G[i][2] * c2;
    }
    for (Py_ssize_t a = 0; a < n; a++) {
        double *row = P + a * n + t0;
        double c0 = row[0], c1 = row[1], c2 = row[2];
        for (int i = 0; i < 3; i++)
            row[i] = c0 * G[i][0] + c1 * G[i][1] + c2 * G[i][2];
    }
}

/* A square float64 matrix of at least 15×15 (the filter's P), its side in *n. */
static int get_P(PyObject *obj, Py_buffer *view, Py_ssize_t *n, int writable)
{
    if (get_doubles(obj, view, -1, writable, "P") < 0)
        return -1;
    *n = (Py_ssize_t)sqrt((double)(view->len / 8));
    if (*n * *n * 8 != view->len || *n < N_CORE) {
        PyBuffer_Release(view);
        PyErr_SetString(PyExc_ValueError, "P must be square, at least 15x15");
        return -1;
    }
    return 0;
}

/* turn_attitude_covariance(P, G) — P ← T P Tᵀ in place, T = I but its attitude block, the
 * 3×3 G given row by row (Eskf.rotate_heading, both of its turns). */
static PyObject *core_turn_attitude_covariance(PyObject *self, PyObject *const *args,
                                               Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "turn_attitude_covariance takes 2 arguments");
        return NULL;
    }
    double g[9], G[3][3];
    if (uwbd_get_vec(args[1], g, 9, "G"))
        return NULL;
    for (int i = 0; i < 9; i++)
        G[i / 3][i % 3] = g[i];
    Py_buffer Pb;
    Py_ssize_t n;
    if (get_P(args[0], &Pb, &n, 1) < 0)
        return NULL;
    transform_attitude((double *)Pb.buf, n, G);
    PyBuffer_Release(&Pb);
    Py_RETURN_NONE;
}

/* P ← (P + Pᵀ)/2, then the error reset P ← G P Gᵀ with G = I except its attitude block
 * I − ½[δθ]× (in place; n×n). */
static void reset_P(double *P, Py_ssize_t n, const double th[3])
{
    for (Py_ssize_t a = 0; a < n; a++)
        for (Py_ssize_t b = a + 1; b < n; b++) {
            double m = 0.5 * (P[a * n + b] + P[b * n + a]);
            P[a * n + b] = m;
            P[b * n + a] = m;
        }
    /* G_th = I − ½[δθ]× */
    double G[3][3] = {{1.0, 0.5 * th[2], -0.5 * th[1]},
                      {-0.5 * th[2], 1.0, 0.5 * th[0]},
                      {0.5 * th[1], -0.5 * th[0], 1.0}};
    transform_attitude(P, n, G);
}

/* reset_covariance(P, dtheta) — after a fused update, in place on P (n×n):
 * P ← (P + Pᵀ)/2, then the error reset P ← G P Gᵀ with G = I except its attitude block
 * I − ½[δθ]× (eskf: sequential_update's symmetrising and Eskf.inject's covariance part). */
static PyObject *core_reset_covariance(PyObject *self, PyObject *const *args,
                                       Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "reset_covariance takes 2 arguments");
        return NULL;
    }
    double th[3];
    if (uwbd_get_vec(args[1], th, 3, "dtheta"))
        return NULL;
    Py_buffer Pb;
    Py_ssize_t n;
    if (get_P(args[0], &Pb, &n, 1) < 0)
        return NULL;
    reset_P((double *)Pb.buf, n, th);
    PyBuffer_Release(&Pb);
    Py_RETURN_NONE;
}

/* markov_step(P, columns, phi, var, b_r, decay, symmetrise)
 * Eskf._markov_step in place: the Gauss–Markov states (their P columns, ascending) decay
 * by phi (e^(−T/τ), numpy's, given): their rows, then their columns of P times phi, their
 * variances plus var (1 − phi²), their b_r and epoch decays (None: not kept) times phi;
 * with symmetrise,
 * P ← (P + Pᵀ)/2 too, as numpy's 0.5 * (P + P.T) makes it (Eskf.propagate next). */
static PyObject *core_markov_step(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 7 || !PyTuple_Check(args[1])) {
        PyErr_SetString(PyExc_TypeError,
                        "markov_step(P, columns, phi, var, b_r, decay, symmetrise)");
        return NULL;
    }
    int symmetrise = PyObject_IsTrue(args[6]);
    if (symmetrise < 0)
        return NULL;
    Py_ssize_t m = PyTuple_GET_SIZE(args[1]), n = 0;
    Py_ssize_t *cols = PyMem_Malloc(sizeof(Py_ssize_t) * (m > 0 ? m : 1));
    if (cols == NULL)
        return PyErr_NoMemory();
    Py_buffer view[5]; /* P, phi, var, b_r, decay */
    int got = 0;
    PyObject *out = NULL;
    if (get_P(args[0], &view[0], &n, 1) < 0)
        goto done;
    got = 1;
    for (Py_ssize_t a = 0; a < m; a++) {
        cols[a] = PyLong_AsSsize_t(PyTuple_GET_ITEM(args[1], a));
        if (cols[a] < N_CORE || cols[a] >= n || (a > 0 && cols[a] <= cols[a - 1])) {
            if (!PyErr_Occurred())
                PyErr_SetString(PyExc_ValueError, "markov_step: columns out of range or order");
            goto done;
        }
    }
    if (get_doubles(args[2], &view[1], m, 0, "phi") < 0)
        goto done;
    got = 2;
    if (get_doubles(args[3], &view[2], m, 0, "var") < 0)
        goto done;
    got = 3;
    if (get_doubles(args[4], &view[3], n - N_CORE, 1, "b_r") < 0)
        goto done;
    got = 4;
    int decays = args[5] != Py_None; /* the epoch's decays kept (for the smoother) */
    if (decays && get_doubles(args[5], &view[4], n - N_CORE, 1, "decay") < 0)
        goto done;
    got = 4 + decays;
    double *P = (double *)view[0].buf, *b_r = (double *)view[3].buf;
    double *decay = decays ? (double *)view[4].buf : NULL;
    const double *phi = (const double *)view[1].buf, *var = (const double *)view[2].buf;
    for (Py_ssize_t a = 0; a < m; a++)
        for (Py_ssize_t j = 0; j < n; j++)
            P[cols[a] * n + j] *= phi[a];
    for (Py_ssize_t i = 0; i < n; i++)
        for (Py_ssize_t a = 0; a < m; a++)
            P[i * n + cols[a]] *= phi[a];
    for (Py_ssize_t a = 0; a < m; a++) {
        P[cols[a] * n + cols[a]] += var[a] * (1.0 - phi[a] * phi[a]);
        b_r[cols[a] - N_CORE] *= phi[a];
        if (decays)
            decay[cols[a] - N_CORE] *= phi[a];
    }
    if (symmetrise)
        for (Py_ssize_t i = 0; i < n; i++)
            for (Py_ssize_t j = i; j < n; j++)
                P[i * n + j] = P[j * n + i] = 0.5 * (P[i * n + j] + P[j * n + i]);
    out = Py_NewRef(Py_None);
done:
    for (int i = 0; i < got; i++)
        PyBuffer_Release(&view[i]);
    PyMem_Free(cols);
    return out;
}

/* The nominal state a fused update corrects: p, v, q, b_g, b_a from the caller's lists
 * (p, v, b_g and b_a are written back in place; q is returned anew, as in Python). */
typedef struct {
    double p[3], v[3], q[4], bg[3], ba[3];
    PyObject *p_list, *v_list, *bg_list, *ba_list;
} Nominal;

static int get_nominal(PyObject *const *args, Nominal *s)
{
    if (uwbd_get_vec(args[0], s->p, 3, "p") || uwbd_get_vec(args[1], s->v, 3, "v") ||
        uwbd_get_vec(args[2], s->q, 4, "q") || uwbd_get_vec(args[3], s->bg, 3, "b_g") ||
        uwbd_get_vec(args[4], s->ba, 3, "b_a"))
        return -1;
    s->p_list = args[0], s->v_list = args[1], s->bg_list = args[3], s->ba_list = args[4];
    if (!PyList_Check(s->p_list) || !PyList_Check(s->v_list) || !PyList_Check(s->bg_list) ||
        !PyList_Check(s->ba_list)) {
        PyErr_SetString(PyExc_TypeError, "p, v, b_g and b_a must be lists");
        return -1;
    }
    return 0;
}

/* The whole of Eskf.sequential_update: scalar_rows on a copy of P; when a row was fused,
 * P takes the copy, symmetrised and reset (reset_P), and the nominal state takes dx
 * (Eskf._inject_nominal: the lists and b_r in place); returns (rows, the new q) — or
 * (rows, None) with P and the state left as they were when no row was fused. */
static PyObject *update_state(double *P, double *dx, double *b_r, Py_ssize_t n,
                              const double *H, const double *y, const double *R, Py_ssize_t m,
                              PyObject *decide, const RowPolicy *pol, Py_ssize_t c0,
                              Py_ssize_t c1, Nominal *s)
{
    if (pol != NULL && pol->count != m) {
        PyErr_SetString(PyExc_ValueError, "decide: one kind per row");
        return NULL;
    }
    double *work = PyMem_Malloc(sizeof(double) * n * n);
    if (work == NULL)
        return PyErr_NoMemory();
    memcpy(work, P, sizeof(double) * n * n);
    int fused;
    PyObject *result = NULL;
    PyObject *rows = scalar_rows(work, dx, n, H, y, R, m, decide, pol, c0, c1, &fused);
    if (rows == NULL)
        goto done;
    if (!fused) {
        result = Py_BuildValue("(OO)", rows, Py_None);
        goto done;
    }
    for (int i = 0; i < 3; i++) {
        s->p[i] += dx[i];
        s->v[i] += dx[3 + i];
        s->bg[i] += dx[9 + i];
        s->ba[i] += dx[12 + i];
    }
    double qn[4];
    turned(s->q, dx[6], dx[7], dx[8], qn);
    if (uwbd_set_list(s->p_list, s->p, 3) || uwbd_set_list(s->v_list, s->v, 3) ||
        uwbd_set_list(s->bg_list, s->bg, 3) || uwbd_set_list(s->ba_list, s->ba, 3))
        goto done;
    for (Py_ssize_t a = N_CORE; a < n; a++)
        b_r[a - N_CORE] += dx[a];
    const double th[3] = {dx[6], dx[7], dx[8]};
    reset_P(work, n, th);
    memcpy(P, work, sizeof(double) * n * n);
    result = Py_BuildValue("(O[dddd])", rows, qn[0], qn[1], qn[2], qn[3]);
done:
    Py_XDECREF(rows);
    PyMem_Free(work);
    return result;
}

/* The weight policy of a call: a RowPolicy tuple (read here; it is callable too, as the
 * Python reference) or any other callable (called back for every row). */
static int get_decide(PyObject *decide, RowPolicy *policy, const RowPolicy **pol)
{
    *pol = NULL;
    if (!PyTuple_Check(decide)) {
        if (PyCallable_Check(decide))
            return 0;
        PyErr_SetString(PyExc_TypeError,
                        "decide: a callable or (kinds, gate_1, robust, c_long, c_short, fix_ok)");
        return -1;
    }
    if (get_policy(decide, policy) < 0)
        return -1;
    *pol = policy;
    return 0;
}

/* update_and_inject(P, H, y, R, decide, c0, c1, dx, p, v, q, b_g, b_a, b_r) -> (rows, q)
 * update_state on rows given; dx (n, zeros) receives the correction. */
static PyObject *core_update_and_inject(PyObject *self, PyObject *const *args,
                                        Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 14) {
        PyErr_SetString(PyExc_TypeError, "update_and_inject takes 14 arguments");
        return NULL;
    }
    Py_ssize_t c0 = PyLong_AsSsize_t(args[5]), c1 = PyLong_AsSsize_t(args[6]);
    if (PyErr_Occurred())
        return NULL;
    RowPolicy policy;
    const RowPolicy *pol;
    Nominal state;
    if (get_decide(args[4], &policy, &pol) < 0 || get_nominal(args + 8, &state) < 0)
        return NULL;
    Py_buffer view[6]; /* P, dx, y, H, R, b_r */
    int got = 0;
    PyObject *result = NULL;
    Py_ssize_t n = 0, m = 0;
    if (get_P(args[0], &view[0], &n, 1) < 0)
        return NULL;
    got = 1;
    if (get_doubles(args[7], &view[1], n, 1, "dx") < 0)
        goto done;
    got = 2;
    if (get_doubles(args[2], &view[2], -1, 0, "y") < 0)
        goto done;
    got = 3;
    m = view[2].len / 8;
    if (get_doubles(args[1], &view[3], m * n, 0, "H") < 0)
        goto done;
    got = 4;
    if (get_doubles(args[3], &view[4], m, 0, "R") < 0)
        goto done;
    got = 5;
    if (get_doubles(args[13], &view[5], n - N_CORE, 1, "b_r") < 0)
        goto done;
    got = 6;
    result = update_state((double *)view[0].buf, (double *)view[1].buf,
                          (double *)view[5].buf, n, (const double *)view[3].buf,
                          (const double *)view[2].buf, (const double *)view[4].buf, m,
                          args[4], pol, c0, c1, &state);
done:
    for (int i = 0; i < got; i++)
        PyBuffer_Release(&view[i]);
    return result;
}

/* -- measurement rows: every UWB message ------------------------------------------------ */

/* measurements.range_rows: per range, with p_ant = p + R l and u = (p_ant − a)/|p_ant − a|,
 * the row h = [u, 0, u (−R [l]×), 0, …, 1 at each of its range-model states] and
 * y = r − |p_ant − a| − Σ b, into H (k×n, zeroed) and y. `columns` holds, per range, the
 * tuple of its range-model state columns. *closest: the smallest distance (NaN sticks). */
static int fill_range_rows(const double pos[3], const double q[4], const double lever[3],
                           const double *anchors, const double *ranges, Py_ssize_t k,
                           const double *b_r, Py_ssize_t n, PyObject *columns, double *H,
                           double *y, double *closest)
{
    if (!PyTuple_Check(columns) || PyTuple_GET_SIZE(columns) != k) {
        PyErr_SetString(PyExc_TypeError, "columns: a tuple with one tuple per range");
        return -1;
    }
    double R[3][3];
    quat_to_matrix(q, R);
    double p_ant[3];
    for (int i = 0; i < 3; i++)
        p_ant[i] = pos[i] + (R[i][0] * lever[0] + R[i][1] * lever[1] + R[i][2] * lever[2]);
    /* M = −R [l]× */
    double sk[3][3] = {{0, -lever[2], lever[1]}, {lever[2], 0, -lever[0]},
                       {-lever[1], lever[0], 0}};
    double M[3][3];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            M[i][j] = -(R[i][0] * sk[0][j] + R[i][1] * sk[1][j] + R[i][2] * sk[2][j]);
    *closest = INFINITY;
    for (Py_ssize_t a = 0; a < k; a++) {
        double d[3];
        for (int i = 0; i < 3; i++)
            d[i] = p_ant[i] - anchors[3 * a + i];
        double dist = sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
        if (isnan(dist) || dist < *closest) /* NaN sticks: the caller's test fails */
            *closest = dist;
        double *h = H + a * n;
        double u[3] = {d[0] / dist, d[1] / dist, d[2] / dist};
        for (int i = 0; i < 3; i++) {
            h[i] = u[i];
            h[6 + i] = u[0] * M[0][i] + u[1] * M[1][i] + u[2] * M[2][i];
        }
        double model = dist;
        PyObject *cols = PyTuple_GET_ITEM(columns, a);
        if (!PyTuple_Check(cols)) {
            PyErr_SetString(PyExc_TypeError, "columns: a tuple with one tuple per range");
            return -1;
        }
        for (Py_ssize_t c = 0; c < PyTuple_GET_SIZE(cols); c++) {
            Py_ssize_t col = PyLong_AsSsize_t(PyTuple_GET_ITEM(cols, c));
            if (col < N_CORE || col >= n) {
                if (!PyErr_Occurred())
                    PyErr_SetString(PyExc_ValueError, "a range-model column out of range");
                return -1;
            }
            h[col] = 1.0;
            model += b_r[col - N_CORE];
        }
        y[a] = ranges[a] - model;
    }
    return 0;
}

/* fuse_ranges on the epoch's own numbers (anchors k×3, ranges, var: k each), the rest as
 * fuse_ranges takes them (nominal: p, v, q, b_g, b_a): what core_fuse_ranges and
 * epoch_step (_epoch.c) share. (rows, q), None or NULL with an error set. */
PyObject *uwbd_fuse_ranges_on(PyObject *P_obj, PyObject *dx_obj, PyObject *b_r_obj,
                              PyObject *const *nominal, const double lever[3],
                              const double *anchors, const double *ranges, const double *var,
                              Py_ssize_t k, PyObject *columns, PyObject *H_obj,
                              PyObject *y_obj, PyObject *R_obj, PyObject *decide,
                              Py_ssize_t c0, Py_ssize_t c1)
{
    RowPolicy policy;
    const RowPolicy *pol;
    Nominal state;
    if (get_decide(decide, &policy, &pol) < 0 || get_nominal(nominal, &state) < 0)
        return NULL;
    Py_buffer view[6]; /* P, dx, b_r, y_extra, H_extra, R_extra */
    int got = 0;
    PyObject *result = NULL;
    double *H = NULL;
    Py_ssize_t n = 0;
    if (get_P(P_obj, &view[0], &n, 1) < 0)
        return NULL;
    got = 1;
    if (get_doubles(dx_obj, &view[1], n, 1, "dx") < 0)
        goto done;
    got = 2;
    if (get_doubles(b_r_obj, &view[2], n - N_CORE, 1, "b_r") < 0)
        goto done;
    got = 3;
    if (get_doubles(y_obj, &view[3], -1, 0, "y_extra") < 0)
        goto done;
    got = 4;
    Py_ssize_t e = view[3].len / 8, m = k + e;
    if (get_doubles(H_obj, &view[4], e * n, 0, "H_extra") < 0)
        goto done;
    got = 5;
    if (get_doubles(R_obj, &view[5], e, 0, "R_extra") < 0)
        goto done;
    got = 6;
    H = PyMem_Calloc((size_t)(m * n + 2 * m), sizeof(double));
    if (H == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    double *y = H + m * n, *R = y + m, closest;
    if (fill_range_rows(state.p, state.q, lever, anchors, ranges, k,
                        (const double *)view[2].buf, n, columns, H, y, &closest) < 0)
        goto done;
    if (!(closest >= 1e-3)) {
        result = Py_NewRef(Py_None);
        goto done;
    }
    memcpy(R, var, sizeof(double) * k);
    memcpy(H + k * n, view[4].buf, sizeof(double) * e * n);
    memcpy(y + k, view[3].buf, sizeof(double) * e);
    memcpy(R + k, view[5].buf, sizeof(double) * e);
    result = update_state((double *)view[0].buf, (double *)view[1].buf,
                          (double *)view[2].buf, n, H, y, R, m, decide, pol, c0, c1, &state);
done:
    PyMem_Free(H);
    for (int i = 0; i < got; i++)
        PyBuffer_Release(&view[i]);
    return result;
}

/* fuse_ranges(P, dx, p, v, q, b_g, b_a, b_r, lever, anchors (k×3), ranges (k), var (k),
 *             columns, H_extra (m×n), y_extra (m), R_extra (m), decide, c0, c1)
 * -> (rows, q) or None
 * A tight epoch in one call: the range rows (fill_range_rows), then the extra rows (ZUPT,
 * NHC, height), through update_state. None, with nothing changed, when an antenna is
 * within 1 mm of an anchor or a distance is NaN (the caller takes the reference, which
 * drops such a range). */
static PyObject *core_fuse_ranges(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 19) {
        PyErr_SetString(PyExc_TypeError, "fuse_ranges takes 19 arguments");
        return NULL;
    }
    Py_ssize_t c0 = PyLong_AsSsize_t(args[17]), c1 = PyLong_AsSsize_t(args[18]);
    if (PyErr_Occurred())
        return NULL;
    double lever[3];
    if (uwbd_get_vec(args[8], lever, 3, "lever"))
        return NULL;
    Py_buffer view[3]; /* ranges, anchors, var */
    int got = 0;
    PyObject *result = NULL;
    if (get_doubles(args[10], &view[0], -1, 0, "ranges") < 0)
        return NULL;
    got = 1;
    Py_ssize_t k = view[0].len / 8;
    if (get_doubles(args[9], &view[1], 3 * k, 0, "anchors") < 0)
        goto done;
    got = 2;
    if (get_doubles(args[11], &view[2], k, 0, "var") < 0)
        goto done;
    got = 3;
    PyObject *const nominal[5] = {args[2], args[3], args[4], args[5], args[6]};
    result = uwbd_fuse_ranges_on(args[0], args[1], args[7], nominal, lever,
                                 (const double *)view[1].buf, (const double *)view[0].buf,
                                 (const double *)view[2].buf, k, args[12], args[13], args[14],
                                 args[15], args[16], c0, c1);
done:
    for (int i = 0; i < got; i++)
        PyBuffer_Release(&view[i]);
    return result;
}

/* -- Gauss–Newton multilateration: every UWB fix ----------------------------------------- */

/* Solve the dims×dims system A z = b (dims 2 or 3) by Gaussian elimination with partial
 * pivoting, as LAPACK's LU does; -1 when a pivot is exactly zero (numpy: LinAlgError). */
static int solve_small(int dims, double A[3][3], double b[3], double z[3])
{
    double M[3][4];
    for (int i = 0; i < dims; i++) {
        for (int j = 0; j < dims; j++)
            M[i][j] = A[i][j];
        M[i][dims] = b[i];
    }
    for (int c = 0; c < dims; c++) {
        int piv = c;
        for (int r = c + 1; r < dims; r++)
            if (fabs(M[r][c]) > fabs(M[piv][c]))
                piv = r;
        if (M[piv][c] == 0.0)
            return -1;
        if (piv != c)
            for (int j = 0; j <= dims; j++) {
                double t = M[c][j];
                M[c][j] = M[piv][j];
                M[piv][j] = t;
            }
        for (int r = c + 1; r < dims; r++) {
            double f = M[r][c] / M[c][c];
            for (int j = c; j <= dims; j++)
                M[r][j] -= f * M[c][j];
        }
    }
    for (int i = dims - 1; i >= 0; i--) {
        double s = M[i][dims];
        for (int j = i + 1; j < dims; j++)
            s -= M[i][j] * z[j];
        z[i] = s / M[i][i];
    }
    return 0;
}

static int normal_matrix(const double *anchors, Py_ssize_t k, const double x[3], int dims,
                         const double *ranges, double JtJ[3][3], double Jtr[3])
{
    for (int i = 0; i < 3; i++) {
        Jtr[i] = 0.0;
        for (int j = 0; j < 3; j++)
            JtJ[i][j] = 0.0;
    }
    for (Py_ssize_t a = 0; a < k; a++) {
        double d[3], dist;
        for (int i = 0; i < 3; i++)
            d[i] = x[i] - anchors[3 * a + i];
        dist = sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
        if (dist < 1e-6)
            return -1;
        double r = ranges == NULL ? 0.0 : dist - ranges[a];
        for (int i = 0; i < dims; i++) {
            double ji = d[i] / dist;
            Jtr[i] += ji * r;
            for (int j = 0; j < dims; j++)
                JtJ[i][j] += ji * (d[j] / dist);
        }
    }
    return 0;
}

/* out (3×3, row-major) = A⁻¹ in its top-left dims×dims, zero elsewhere */
static int inverse(int dims, double A[3][3], double *out)
{
    for (int i = 0; i < 9; i++)
        out[i] = 0.0;
    for (int c = 0; c < dims; c++) {
        double e[3] = {0.0, 0.0, 0.0}, col[3];
        e[c] = 1.0;
        if (solve_small(dims, A, e, col) < 0)
            return -1;
        for (int r = 0; r < dims; r++)
            out[3 * r + c] = col[r];
    }
    return 0;
}

/* lsq._solve's iteration (see gauss_newton below) on k anchors and ranges, x in place;
 * the iterations, or 0 for no fix; out (3×3) the last step's (JᵀJ)⁻¹ when there is one. */
static long iterate(const double *anchors, const double *ranges, Py_ssize_t k, double x[3],
                    int dims, long max_iter, double converged, double accept_last,
                    double *out)
{
    long iteration = 0, result = 0;
    double JtJ[3][3];
    for (;;) {
        iteration++;
        double Jtr[3], step[3];
        if (normal_matrix(anchors, k, x, dims, ranges, JtJ, Jtr) < 0)
            break;
        for (int i = 0; i < dims; i++)
            Jtr[i] = -Jtr[i];
        if (solve_small(dims, JtJ, Jtr, step) < 0)
            break;
        double norm = 0.0;
        for (int i = 0; i < dims; i++) {
            x[i] += step[i];
            norm += step[i] * step[i];
        }
        norm = sqrt(norm);
        if (norm < converged) {
            result = iteration;
            break;
        }
        if (iteration == max_iter) {
            result = norm <= accept_last ? iteration : 0; /* NaN: no fix */
            break;
        }
    }
    if (result && inverse(dims, JtJ, out) < 0)
        result = 0;
    return result;
}

/* gauss_newton(anchors (k×3), ranges (k), x (3, in place), dims, max_iterations,
 *              converged_m, accept_last_m, out (3×3)) -> iterations, or 0 for no fix
 * lsq._solve's iteration: steps (JᵀJ) δ = −Jᵀ r on the first `dims` coordinates until a
 * step is below converged_m; after max_iterations a last step above accept_last_m is no
 * fix; a range from an anchor closer than 1 µm or a singular JᵀJ is no fix either. `out`
 * gets (JᵀJ)⁻¹ of the last step in its top-left dims×dims, the rest zero: the fix's
 * covariance over σ². */
static PyObject *core_gauss_newton(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 8) {
        PyErr_SetString(PyExc_TypeError, "gauss_newton takes 8 arguments");
        return NULL;
    }
    long dims = PyLong_AsLong(args[3]);
    if (dims == -1 && PyErr_Occurred())
        return NULL;
    long max_iter = PyLong_AsLong(args[4]);
    if (max_iter == -1 && PyErr_Occurred())
        return NULL;
    double converged = PyFloat_AsDouble(args[5]);
    if (converged == -1.0 && PyErr_Occurred())
        return NULL;
    double accept_last = PyFloat_AsDouble(args[6]);
    if (accept_last == -1.0 && PyErr_Occurred())
        return NULL;
    if (dims != 2 && dims != 3) {
        PyErr_SetString(PyExc_ValueError, "dims must be 2 or 3");
        return NULL;
    }
    if (max_iter < 1) {
        PyErr_SetString(PyExc_ValueError, "max_iterations must be at least 1");
        return NULL;
    }
    Py_buffer Ab, rb, xb, ob;
    if (get_doubles(args[7], &ob, 9, 1, "out") < 0)
        return NULL;
    if (get_doubles(args[1], &rb, -1, 0, "ranges") < 0) {
        PyBuffer_Release(&ob);
        return NULL;
    }
    Py_ssize_t k = rb.len / 8;
    if (get_doubles(args[0], &Ab, 3 * k, 0, "anchors") < 0) {
        PyBuffer_Release(&rb);
        PyBuffer_Release(&ob);
        return NULL;
    }
    if (get_doubles(args[2], &xb, 3, 1, "x") < 0) {
        PyBuffer_Release(&rb);
        PyBuffer_Release(&Ab);
        PyBuffer_Release(&ob);
        return NULL;
    }
    long result = iterate((const double *)Ab.buf, (const double *)rb.buf, k,
                          (double *)xb.buf, (int)dims, max_iter, converged, accept_last,
                          (double *)ob.buf);
    PyBuffer_Release(&rb);
    PyBuffer_Release(&Ab);
    PyBuffer_Release(&xb);
    PyBuffer_Release(&ob);
    return PyLong_FromLong(result);
}

/* The leverage of each of k ranges at x, h_ii = J_i (JᵀJ)⁻¹ J_iᵀ with J the unit vectors
 * from the anchors (their first dims coordinates), into h; -1 if JᵀJ is singular. */
static int leverage_values(const double *anchors, Py_ssize_t k, const double x[3], int dims,
                           double *h)
{
    double JtJ[3][3], unused[3], inv[9];
    if (normal_matrix(anchors, k, x, dims, NULL, JtJ, unused) < 0 ||
        inverse(dims, JtJ, inv) < 0)
        return -1;
    for (Py_ssize_t a = 0; a < k; a++) {
        double d[3], dist, u[3];
        for (int i = 0; i < 3; i++)
            d[i] = x[i] - anchors[3 * a + i];
        dist = sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
        for (int i = 0; i < dims; i++)
            u[i] = d[i] / dist;
        h[a] = 0.0;
        for (int i = 0; i < dims; i++)
            for (int j = 0; j < dims; j++)
                h[a] += u[i] * inv[3 * i + j] * u[j];
    }
    return 0;
}

/* leverages(anchors (k×3), x (3), dims) -> [h_ii] or None if JᵀJ is singular
 * multilaterate's studentised residuals (leverage_values). */
static PyObject *core_leverages(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "leverages takes 3 arguments");
        return NULL;
    }
    long dims = PyLong_AsLong(args[2]);
    if (dims == -1 && PyErr_Occurred())
        return NULL;
    if (dims != 2 && dims != 3) {
        PyErr_SetString(PyExc_ValueError, "dims must be 2 or 3");
        return NULL;
    }
    Py_buffer Ab, xb;
    if (get_doubles(args[0], &Ab, -1, 0, "anchors") < 0)
        return NULL;
    if (get_doubles(args[1], &xb, 3, 0, "x") < 0) {
        PyBuffer_Release(&Ab);
        return NULL;
    }
    PyObject *out = NULL;
    Py_ssize_t k = Ab.len / 24;
    double *h = NULL;
    if (Ab.len % 24 != 0) {
        PyErr_SetString(PyExc_ValueError, "anchors: k x 3 numbers expected");
        goto done;
    }
    h = PyMem_Malloc(sizeof(double) * (k > 0 ? k : 1));
    if (h == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    if (leverage_values((const double *)Ab.buf, k, (const double *)xb.buf, (int)dims, h) < 0) {
        out = Py_NewRef(Py_None);
        goto done;
    }
    out = uwbd_floats(h, k, 1);
done:
    PyMem_Free(h);
    PyBuffer_Release(&Ab);
    PyBuffer_Release(&xb);
    return out;
}

/* A fix of the ranges in `keep` (k flags) from x (in place): iterate on them gathered into
 * work (4 k doubles); its residuals into res (NaN for ranges not kept). */
static long fix_of(const double *anchors, const double *ranges, Py_ssize_t k,
                   const char *keep, double x[3], int dims, long max_iter, double converged,
                   double accept_last, double *inv, double *work, double *res)
{
    double *sub_a = work, *sub_r = work + 3 * k;
    Py_ssize_t m = 0;
    for (Py_ssize_t a = 0; a < k; a++)
        if (keep[a]) {
            memcpy(sub_a + 3 * m, anchors + 3 * a, 3 * sizeof(double));
            sub_r[m++] = ranges[a];
        }
    long it = iterate(sub_a, sub_r, m, x, dims, max_iter, converged, accept_last, inv);
    for (Py_ssize_t a = 0; a < k; a++) {
        double d[3];
        for (int i = 0; i < 3; i++)
            d[i] = x[i] - anchors[3 * a + i];
        res[a] = keep[a] ? sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) - ranges[a] : NAN;
    }
    return it;
}

static PyObject *fix_tuple(const double x[3], const double *inv, const double *res,
                           const char *keep, Py_ssize_t k, long iterations)
{
    PyObject *r = PyList_New(k), *u = PyList_New(k);
    if (r == NULL || u == NULL) {
        Py_XDECREF(r);
        Py_XDECREF(u);
        return NULL;
    }
    for (Py_ssize_t a = 0; a < k; a++) {
        PyObject *f = PyFloat_FromDouble(res[a]);
        if (f == NULL) {
            Py_DECREF(r);
            Py_DECREF(u);
            return NULL;
        }
        PyList_SET_ITEM(r, a, f);
        PyList_SET_ITEM(u, a, Py_NewRef(keep[a] ? Py_True : Py_False));
    }
    return Py_BuildValue("([ddd][ddddddddd]NNl)", x[0], x[1], x[2], inv[0], inv[1], inv[2],
                         inv[3], inv[4], inv[5], inv[6], inv[7], inv[8], r, u, iterations);
}

/* multilaterate(anchors (k×3), ranges (k), x0 (3), dims, sigma, outlier_sigma,
 *               max_iterations, converged_m, accept_last_m)
 * -> (x, (JᵀJ)⁻¹ (9), residuals (k), used (k), iterations), None for no fix, or
 *    NotImplemented where the reference must decide (a singular JᵀJ for the leverages, a
 *    NaN studentised residual)
 * lsq.multilaterate from a start point x0 (with dims 2, its z the height held): the fix of
 * all ranges; with more than dims + 1 of them, the range of the largest studentised
 * residual r_i / (σ √max(1 − h_ii, 1e-6)) dropped when that exceeds outlier_sigma, and the
 * fix solved again from the first (the first kept where the second fails). */
static PyObject *core_multilaterate(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 9) {
        PyErr_SetString(PyExc_TypeError, "multilaterate takes 9 arguments");
        return NULL;
    }
    double x[3];
    if (uwbd_get_vec(args[2], x, 3, "x0"))
        return NULL;
    long dims = PyLong_AsLong(args[3]), max_iter = PyLong_AsLong(args[6]);
    double sigma = PyFloat_AsDouble(args[4]), outlier = PyFloat_AsDouble(args[5]);
    double converged = PyFloat_AsDouble(args[7]), accept_last = PyFloat_AsDouble(args[8]);
    if (PyErr_Occurred())
        return NULL;
    if ((dims != 2 && dims != 3) || max_iter < 1) {
        PyErr_SetString(PyExc_ValueError, "dims 2 or 3, max_iterations at least 1");
        return NULL;
    }
    Py_buffer Ab, rb;
    if (get_doubles(args[1], &rb, -1, 0, "ranges") < 0)
        return NULL;
    Py_ssize_t k = rb.len / 8;
    if (get_doubles(args[0], &Ab, 3 * k, 0, "anchors") < 0) {
        PyBuffer_Release(&rb);
        return NULL;
    }
    const double *anchors = (const double *)Ab.buf, *ranges = (const double *)rb.buf;
    PyObject *out = NULL;
    /* work: 4k gathered, k residuals, k leverages, k second residuals; keep: k flags */
    double *work = PyMem_Malloc(sizeof(double) * (7 * k + 1));
    char *keep = PyMem_Malloc((size_t)k + 1);
    if (work == NULL || keep == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    double *res = work + 4 * k, *lev = res + k, *res2 = lev + k, inv[9], inv2[9];
    memset(keep, 1, (size_t)k);
    if (k < dims) {
        out = Py_NewRef(Py_None);
        goto done;
    }
    long it = fix_of(anchors, ranges, k, keep, x, (int)dims, max_iter, converged,
                     accept_last, inv, work, res);
    if (it == 0) {
        out = Py_NewRef(Py_None);
        goto done;
    }
    if (k <= dims + 1) {
        out = fix_tuple(x, inv, res, keep, k, it);
        goto done;
    }
    if (leverage_values(anchors, k, x, (int)dims, lev) < 0) {
        out = Py_NewRef(Py_NotImplemented);
        goto done;
    }
    Py_ssize_t worst = 0;
    double worst_student = -1.0;
    for (Py_ssize_t a = 0; a < k; a++) {
        double spare = 1.0 - lev[a];
        double student = fabs(res[a]) / (sigma * sqrt(spare > 1e-6 ? spare : 1e-6));
        if (isnan(student)) {
            out = Py_NewRef(Py_NotImplemented);
            goto done;
        }
        if (student > worst_student) {
            worst_student = student;
            worst = a;
        }
    }
    if (worst_student <= outlier) {
        out = fix_tuple(x, inv, res, keep, k, it);
        goto done;
    }
    keep[worst] = 0;
    double x2[3] = {x[0], x[1], x[2]};
    long it2 = fix_of(anchors, ranges, k, keep, x2, (int)dims, max_iter, converged,
                      accept_last, inv2, work, res2);
    if (it2 == 0) {
        keep[worst] = 1;
        out = fix_tuple(x, inv, res, keep, k, it);
    } else {
        out = fix_tuple(x2, inv2, res2, keep, k, it2);
    }
done:
    PyMem_Free(work);
    PyMem_Free(keep);
    PyBuffer_Release(&Ab);
    PyBuffer_Release(&rb);
    return out;
}

/* -- outputs and checks ----------------------------------------------------------------- */

/* pose_numbers(P, q, p, v, aligned, max_yaw_sigma)
 * -> (covariance (36), σ_xy, heading observable, position (3), velocity (3), xyzw (4)),
 *    or None when a number is not finite (Filter.pose then restarts the filter)
 * Filter.pose's numbers: the covariance over position and the attitude error turned into
 * the navigation frame, [[Ppp, Ppθ Rᵀ], [R Pθp, R Pθθ Rᵀ]], row-major, made symmetric as
 * (M + Mᵀ)/2; while the heading is not aligned its yaw row and column are 0 and its
 * variance π² (_yaw_unknown); finite as the reference tells it (one sum, in its order). */
PyObject *uwbd_pose_numbers(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 6) {
        PyErr_SetString(PyExc_TypeError, "pose_numbers takes 6 arguments");
        return NULL;
    }
    double q[4], p[3], v[3];
    if (uwbd_get_vec(args[1], q, 4, "q") || uwbd_get_vec(args[2], p, 3, "p") ||
        uwbd_get_vec(args[3], v, 3, "v"))
        return NULL;
    int aligned = PyObject_IsTrue(args[4]);
    double max_yaw_sigma = PyFloat_AsDouble(args[5]);
    if (aligned < 0 || PyErr_Occurred())
        return NULL;
    Py_buffer Pb;
    Py_ssize_t n;
    if (get_P(args[0], &Pb, &n, 0) < 0)
        return NULL;
    const double *P = (const double *)Pb.buf;
    /* the reference's T P Tᵀ spreads a NaN or inf anywhere in P[:9, :9] (0 × inf is NaN),
     * the velocity block too, which the product below never reads */
    for (int i = 0; i < 9; i++)
        for (int j = 0; j < 9; j++)
            if (!isfinite(P[i * n + j])) {
                PyBuffer_Release(&Pb);
                Py_RETURN_NONE;
            }
    double R[3][3];
    quat_to_matrix(q, R);
    /* T (6×9) = [[I, 0, 0], [0, 0, R]] over (p, v, θ); M = T P Tᵀ */
    double TP[6][9];
    for (int j = 0; j < 9; j++) {
        for (int i = 0; i < 3; i++)
            TP[i][j] = P[i * n + j];
        for (int i = 0; i < 3; i++)
            TP[3 + i][j] = R[i][0] * P[6 * n + j] + R[i][1] * P[7 * n + j]
                + R[i][2] * P[8 * n + j];
    }
    PyBuffer_Release(&Pb);
    double M[6][6], cov[36];
    for (int i = 0; i < 6; i++) {
        for (int j = 0; j < 3; j++)
            M[i][j] = TP[i][j];
        for (int j = 0; j < 3; j++)
            M[i][3 + j] = TP[i][6] * R[j][0] + TP[i][7] * R[j][1] + TP[i][8] * R[j][2];
    }
    for (int i = 0; i < 6; i++)
        for (int j = 0; j < 6; j++)
            cov[6 * i + j] = 0.5 * (M[i][j] + M[j][i]);
    if (!aligned) { /* held, its σ a placeholder: to a subscriber, yaw is unknown */
        for (int i = 0; i < 6; i++)
            cov[6 * i + 5] = cov[30 + i] = 0.0;
        cov[35] = M_PI * M_PI;
    }
    /* sum(p) + sum(v) + w + x + y + z + sum(covariance), as Python adds them */
    double s = p[0] + p[1] + p[2], sv = v[0] + v[1] + v[2], sc = 0.0;
    for (int i = 0; i < 36; i++)
        sc += cov[i];
    if (!isfinite(s + sv + q[0] + q[1] + q[2] + q[3] + sc))
        Py_RETURN_NONE;
    double xy = cov[0] + cov[7], yaw = cov[35];
    /* max(x, 0.0) as Python takes it: x unless 0.0 is larger (-0.0 and NaN stay) */
    double sigma_xy = sqrt(0.0 > xy ? 0.0 : xy);
    int observable = aligned && sqrt(0.0 > yaw ? 0.0 : yaw) < max_yaw_sigma;
    /* (cov, σ_xy, observable, p, v, xyzw), made item by item (Py_BuildValue parses its
     * format on every pose) */
    const double xyzw[4] = {q[1], q[2], q[3], q[0]};
    PyObject *out = PyTuple_New(6);
    if (out == NULL)
        return NULL;
    PyObject *items[6] = {uwbd_floats(cov, 36, 0), PyFloat_FromDouble(sigma_xy),
                          PyBool_FromLong(observable), uwbd_floats(p, 3, 0),
                          uwbd_floats(v, 3, 0), uwbd_floats(xyzw, 4, 0)};
    for (int i = 0; i < 6; i++) {
        if (items[i] == NULL)
            Py_CLEAR(out);
        if (out != NULL)
            PyTuple_SET_ITEM(out, i, items[i]);
        else
            Py_XDECREF(items[i]);
    }
    return out;
}

/* A variance of P above its limit or below zero (Eskf.clamp_covariance's test; NaN is
 * neither, as in numpy's comparisons): 1, 0, or -1 with an error set. */
int uwbd_diagonal_out_of_bounds(PyObject *P_obj, PyObject *limit)
{
    Py_buffer Pb, Lb;
    Py_ssize_t n;
    if (get_P(P_obj, &Pb, &n, 0) < 0)
        return -1;
    if (get_doubles(limit, &Lb, n, 0, "limit") < 0) {
        PyBuffer_Release(&Pb);
        return -1;
    }
    const double *P = (const double *)Pb.buf, *L = (const double *)Lb.buf;
    int out = 0;
    for (Py_ssize_t i = 0; i < n && !out; i++)
        out = P[i * n + i] > L[i] || P[i * n + i] < 0.0;
    PyBuffer_Release(&Pb);
    PyBuffer_Release(&Lb);
    return out;
}

/* Every entry of P finite and of magnitude below `bound`: 1, 0 (not so), or -1 with an
 * error set. */
int uwbd_all_finite_below(PyObject *P_obj, double bound)
{
    Py_buffer Pb;
    Py_ssize_t n;
    if (get_P(P_obj, &Pb, &n, 0) < 0)
        return -1;
    const double *P = (const double *)Pb.buf;
    int ok = 1;
    for (Py_ssize_t i = 0; i < n * n && ok; i++)
        ok = fabs(P[i]) < bound; /* (false for NaN) */
    PyBuffer_Release(&Pb);
    return ok;
}

/* diagonal_out_of_bounds(P, limit) -> bool */
static PyObject *core_diagonal_out_of_bounds(PyObject *self, PyObject *const *args,
                                             Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "diagonal_out_of_bounds takes 2 arguments");
        return NULL;
    }
    int out = uwbd_diagonal_out_of_bounds(args[0], args[1]);
    return out < 0 ? NULL : PyBool_FromLong(out);
}

/* -- the rest test's moments ------------------------------------------------------------ */

/* window_moments(samples, span_ns) -> (mean, std) of the six axes over the rows of the last
 * span_ns, or None for fewer than 3 rows: ImuWindow._judge's numpy steps, to the bit. The
 * rows are (t_ns, ax, ay, az, gx, gy, gz) tuples in time order (a deque); numpy takes the
 * times as float64 (np.array of the rows), finds the first row at or after last - span_ns
 * (searchsorted) and sums each axis over the rows in order (a reduction along axis 0 is a
 * running sum), divides by n, and the same for the squared deviations. */
static PyObject *core_window_moments(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "window_moments(samples, span_ns)");
        return NULL;
    }
    double span = PyFloat_AsDouble(args[1]);
    if (span == -1.0 && PyErr_Occurred())
        return NULL;
    Py_ssize_t count = PyObject_Length(args[0]);
    if (count < 0)
        return NULL;
    if (count < 3)
        Py_RETURN_NONE;
    PyObject *it = PyObject_CallMethod(args[0], "__reversed__", NULL);
    if (it == NULL)
        return NULL;
    /* newest first, kept until a row falls before the span; then summed oldest first */
    double *rows = PyMem_Malloc((size_t)count * 6 * sizeof(double));
    if (rows == NULL) {
        Py_DECREF(it);
        return PyErr_NoMemory();
    }
    Py_ssize_t n = 0;
    double start = 0.0;
    PyObject *row;
    while ((row = PyIter_Next(it)) != NULL) {
        int bad = !PyTuple_Check(row) || PyTuple_GET_SIZE(row) != 7;
        double t = bad ? 0.0 : PyFloat_AsDouble(PyTuple_GET_ITEM(row, 0));
        if (!bad && n == 0)
            start = t - span;
        if (!bad && t >= start && n < count) {
            for (int j = 0; j < 6 && !bad; j++) {
                rows[6 * n + j] = PyFloat_AsDouble(PyTuple_GET_ITEM(row, j + 1));
                bad = rows[6 * n + j] == -1.0 && PyErr_Occurred();
            }
            n++;
        } else if (!bad) {
            Py_DECREF(row);
            break;
        }
        Py_DECREF(row);
        if (bad || PyErr_Occurred()) {
            if (!PyErr_Occurred())
                PyErr_SetString(PyExc_TypeError, "window_moments: rows are (t_ns, 6 floats)");
            Py_DECREF(it);
            PyMem_Free(rows);
            return NULL;
        }
    }
    Py_DECREF(it);
    if (PyErr_Occurred()) {
        PyMem_Free(rows);
        return NULL;
    }
    if (n < 3) {
        PyMem_Free(rows);
        Py_RETURN_NONE;
    }
    double mean[6], var[6];
    for (int j = 0; j < 6; j++) {
        double sum = rows[6 * (n - 1) + j]; /* the oldest row first, as numpy starts */
        for (Py_ssize_t k = n - 2; k >= 0; k--)
            sum += rows[6 * k + j];
        mean[j] = sum / (double)n;
        double d = rows[6 * (n - 1) + j] - mean[j];
        double sq = d * d;
        for (Py_ssize_t k = n - 2; k >= 0; k--) {
            d = rows[6 * k + j] - mean[j];
            sq += d * d;
        }
        var[j] = sqrt(sq / (double)n);
    }
    PyMem_Free(rows);
    return Py_BuildValue("((dddddd)(dddddd))", mean[0], mean[1], mean[2], mean[3], mean[4],
                         mean[5], var[0], var[1], var[2], var[3], var[4], var[5]);
}

static PyMethodDef core_methods[] = {
    {"predict", (PyCFunction)(void (*)(void))core_predict, METH_FASTCALL,
     "Eskf.predict: one IMU sample (p, v, sums in place; returns the new q)."},
    {"propagate_core", (PyCFunction)(void (*)(void))core_propagate, METH_FASTCALL,
     "Eskf.propagate's core rows and columns, in place on P and Phi_epoch."},
    {"markov_step", (PyCFunction)(void (*)(void))core_markov_step, METH_FASTCALL,
     "Eskf._markov_step in place (the decays given), and P symmetrised if asked."},
    {"update_and_inject", (PyCFunction)(void (*)(void))core_update_and_inject, METH_FASTCALL,
     "Eskf.sequential_update whole: the rows, then P reset and the state corrected."},
    {"turn_attitude_covariance", (PyCFunction)(void (*)(void))core_turn_attitude_covariance,
     METH_FASTCALL, "P <- T P T^T for T = I but its attitude block G, in place."},
    {"reset_covariance", (PyCFunction)(void (*)(void))core_reset_covariance, METH_FASTCALL,
     "After a fused update: P symmetrised and reset by G, in place."},
    {"fuse_ranges", (PyCFunction)(void (*)(void))core_fuse_ranges, METH_FASTCALL,
     "A tight epoch: the range rows and the extra rows fused in one call (or None)."},
    {"pose_numbers", (PyCFunction)(void (*)(void))uwbd_pose_numbers, METH_FASTCALL,
     "Filter.pose's numbers: covariance, sigma_xy, heading observable, p, v, xyzw."},
    {"diagonal_out_of_bounds", (PyCFunction)(void (*)(void))core_diagonal_out_of_bounds,
     METH_FASTCALL, "Any variance of P above its limit or below zero."},
    {"gauss_newton", (PyCFunction)(void (*)(void))core_gauss_newton, METH_FASTCALL,
     "lsq._solve's Gauss-Newton iteration, in place on x; the iterations, 0: no fix."},
    {"multilaterate", (PyCFunction)(void (*)(void))core_multilaterate, METH_FASTCALL,
     "lsq.multilaterate from a start point: the fix, its outlier test and second fix."},
    {"leverages", (PyCFunction)(void (*)(void))core_leverages, METH_FASTCALL,
     "Each range's leverage at x (multilaterate's outlier test); None if singular."},
    {"window_moments", (PyCFunction)(void (*)(void))core_window_moments, METH_FASTCALL,
     "ImuWindow._judge's mean and std of the six axes over the last span_ns, or None."},
    {"imu_step", (PyCFunction)(void (*)(void))uwbd_imu_step, METH_FASTCALL,
     "Filter.predict's common sample whole (check, rest window, INS step), or None."},
    {"outcomes", (PyCFunction)(void (*)(void))uwbd_outcomes, METH_FASTCALL,
     "EpochFusion._outcomes: each row reported, counted, the health and anchor evidence."},
    {"imu_read", (PyCFunction)(void (*)(void))uwbd_imu_read, METH_FASTCALL,
     "The common IMU read whole (parse, spread, align, check, predict), or None."},
    {"epoch_step", (PyCFunction)(void (*)(void))uwbd_epoch_step, METH_FASTCALL,
     "Filter._update's common UWB message whole (running, aligned, tight), or None."},
    {"pose_step", (PyCFunction)(void (*)(void))uwbd_pose_step, METH_FASTCALL,
     "Filter.pose whole while tracking or aligning without a fault, or NotImplemented."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef core_module = {
    PyModuleDef_HEAD_INIT, "_core",
    "The error-state EKF's hot algebra in C (uwbd/fusion/eskf.py is the reference).", -1,
    core_methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__core(void)
{
    if (uwbd_outcomes_init() < 0)
        return NULL;
    if (uwbd_nominal_init() < 0 || uwbd_imu_read_init() < 0 || uwbd_epoch_init() < 0 ||
        uwbd_pose_init() < 0)
        return NULL;
    return PyModule_Create(&core_module);
}
