/* The numbers of the installation checks (docs/ekf.md §6); the decisions on them stay in
 * Python (uwbd/fusion/checks/anchor_consistency.py and bias_gain.py, which hold the
 * reference of each function here; tests/test_core.py compares the two):
 *
 *   uwbd_single_faults  Baarda's single-fault estimate of each range of an epoch,
 *                       b_j = (S⁻¹ν)_j / (S⁻¹)_jj and its weight (S⁻¹)_jj (the anchor test;
 *                       State.range_check brings ν and S = H P Hᵀ + R)
 *   snapshot_gain       one snapshot's least-squares gain of a position offset: what a
 *                       bias on every range can do (the protection levels' bias term) */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>

#include "_core.h"

/* A (k×k, destroyed) inverted into Ai by Gauss–Jordan elimination with partial pivoting:
 * 0, or -1 when a pivot is exactly zero or not a number (numpy.linalg.inv: LinAlgError). */
static int invert(double *A, Py_ssize_t k, double *Ai)
{
    memset(Ai, 0, sizeof(double) * (size_t)(k * k));
    for (Py_ssize_t i = 0; i < k; i++)
        Ai[i * k + i] = 1.0;
    for (Py_ssize_t c = 0; c < k; c++) {
        Py_ssize_t piv = c;
        for (Py_ssize_t r = c + 1; r < k; r++)
            if (fabs(A[r * k + c]) > fabs(A[piv * k + c]))
                piv = r;
        double pv = A[piv * k + c];
        if (pv == 0.0 || !isfinite(pv))
            return -1;
        if (piv != c)
            for (Py_ssize_t j = 0; j < k; j++) {
                double t = A[c * k + j];
                A[c * k + j] = A[piv * k + j];
                A[piv * k + j] = t;
                t = Ai[c * k + j];
                Ai[c * k + j] = Ai[piv * k + j];
                Ai[piv * k + j] = t;
            }
        for (Py_ssize_t j = 0; j < k; j++) {
            A[c * k + j] /= pv;
            Ai[c * k + j] /= pv;
        }
        for (Py_ssize_t r = 0; r < k; r++) {
            double f = A[r * k + c];
            if (r == c || f == 0.0)
                continue;
            for (Py_ssize_t j = 0; j < k; j++) {
                A[r * k + j] -= f * A[c * k + j];
                Ai[r * k + j] -= f * Ai[c * k + j];
            }
        }
    }
    return 0;
}

int uwbd_single_faults(double *S, const double *nu, Py_ssize_t k, double *b, double *d,
                       double *work)
{
    if (invert(S, k, work) < 0)
        return -1;
    for (Py_ssize_t j = 0; j < k; j++) {
        double g = 0.0;
        for (Py_ssize_t i = 0; i < k; i++)
            g += work[j * k + i] * nu[i];
        d[j] = work[j * k + j];
        b[j] = g / d[j];
    }
    return 0;
}

/* snapshot_gain(rows) -> (gx, gy, gz) or None: the rows are tuples (…, w, ux, uy, uz) whose
 * last four items are a range's weight and the unit vector anchor → tag. The least-squares
 * gain of one position offset, S = (UᵀWU + εI)⁻¹UᵀW (ε = 1e-9 tr), as Σ_j |S_ij| per axis:
 * the most position error a bias of 1 m on every range can make; None when the normal
 * matrix is singular. The reference: bias_gain.snapshot_gain. */
PyObject *uwbd_snapshot_gain(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 1 || !PyList_Check(args[0])) {
        PyErr_SetString(PyExc_TypeError, "snapshot_gain(rows: a list of tuples)");
        return NULL;
    }
    Py_ssize_t k = PyList_GET_SIZE(args[0]);
    double *buf = PyMem_Malloc(sizeof(double) * (size_t)(4 * k + 1));
    if (buf == NULL)
        return PyErr_NoMemory();
    double *w = buf, *U = w + k;
    for (Py_ssize_t a = 0; a < k; a++) {
        PyObject *row = PyList_GET_ITEM(args[0], a);
        Py_ssize_t len = PyTuple_Check(row) ? PyTuple_GET_SIZE(row) : 0;
        if (len < 4) {
            PyMem_Free(buf);
            PyErr_SetString(PyExc_TypeError, "snapshot_gain: rows end in (w, ux, uy, uz)");
            return NULL;
        }
        double v[4];
        for (int j = 0; j < 4; j++) {
            v[j] = PyFloat_AsDouble(PyTuple_GET_ITEM(row, len - 4 + j));
            if (v[j] == -1.0 && PyErr_Occurred()) {
                PyMem_Free(buf);
                return NULL;
            }
        }
        w[a] = v[0];
        U[3 * a] = v[1];
        U[3 * a + 1] = v[2];
        U[3 * a + 2] = v[3];
    }
    double N[9] = {0}, Ni[9];
    for (Py_ssize_t a = 0; a < k; a++)
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++)
                N[3 * i + j] += U[3 * a + i] * (U[3 * a + j] * w[a]);
    double eps = 1e-9 * (N[0] + N[4] + N[8]);
    for (int i = 0; i < 3; i++)
        N[4 * i] += eps;
    if (invert(N, 3, Ni) < 0) {
        PyMem_Free(buf);
        Py_RETURN_NONE;
    }
    double gain[3] = {0, 0, 0};
    for (Py_ssize_t a = 0; a < k; a++)
        for (int i = 0; i < 3; i++)
            gain[i] += fabs((Ni[3 * i] * U[3 * a] + Ni[3 * i + 1] * U[3 * a + 1] +
                             Ni[3 * i + 2] * U[3 * a + 2]) * w[a]);
    PyMem_Free(buf);
    return Py_BuildValue("(ddd)", gain[0], gain[1], gain[2]);
}
