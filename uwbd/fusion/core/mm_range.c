/* The range measurement model of docs/ekf.md §4 (the reference: measurements.range_rows):
 * per range, with the antenna p_t = p + R l and u = (p_t − a)/|p_t − a|,
 *     h = [u, 0, −uᵀ R [l]×, 0, …, 1 at each of its range-model states, uᵀ R at the lever
 *          arm's error states where they are],
 *     y = r − |p_t − a| − Σ b. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>

#include "_core.h"

#define COLUMNS_TYPE "columns: a tuple with one tuple of range-model columns per range"
#define LEVER_TYPE "lever_columns: a tuple of the lever arm's three error-state columns, or ()"

/* Into H (k×n, zeroed) and y; `columns` holds per range the tuple of its range-model state
 * columns, `lever_columns` the lever arm's error states (() or NULL: none). dist (k): each
 * antenna-anchor distance. 0, or -1. */
int uwbd_range_rows(const double p[3], const double q[4], const double lever[3],
                    const double *anchors, const double *ranges, Py_ssize_t k,
                    const double *b_r, Py_ssize_t n, PyObject *columns,
                    PyObject *lever_columns, double *H, double *y, double *dist_out)
{
    if (!PyTuple_Check(columns) || PyTuple_GET_SIZE(columns) != k) {
        PyErr_SetString(PyExc_TypeError, COLUMNS_TYPE);
        return -1;
    }
    Py_ssize_t lc[3], n_lever = lever_columns == NULL ? 0
        : PyTuple_Check(lever_columns) ? PyTuple_GET_SIZE(lever_columns) : -1;
    if (n_lever != 0 && n_lever != 3) {
        PyErr_SetString(PyExc_TypeError, LEVER_TYPE);
        return -1;
    }
    for (Py_ssize_t j = 0; j < n_lever; j++) {
        lc[j] = PyLong_AsSsize_t(PyTuple_GET_ITEM(lever_columns, j));
        if (lc[j] < N_CORE || lc[j] >= n) {
            if (!PyErr_Occurred())
                PyErr_SetString(PyExc_ValueError, "a lever-arm column out of range");
            return -1;
        }
    }
    double R[3][3];
    uwbd_quat_to_matrix(q, R);
    double p_ant[3];
    for (int i = 0; i < 3; i++)
        p_ant[i] = p[i] + (R[i][0] * lever[0] + R[i][1] * lever[1] + R[i][2] * lever[2]);
    /* M = −R [l]× */
    double sk[3][3] = {{0, -lever[2], lever[1]}, {lever[2], 0, -lever[0]},
                       {-lever[1], lever[0], 0}};
    double M[3][3];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            M[i][j] = -(R[i][0] * sk[0][j] + R[i][1] * sk[1][j] + R[i][2] * sk[2][j]);
    for (Py_ssize_t a = 0; a < k; a++) {
        double d[3];
        for (int i = 0; i < 3; i++)
            d[i] = p_ant[i] - anchors[3 * a + i];
        double dist = sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
        dist_out[a] = dist;
        double *h = H + a * n;
        double u[3] = {d[0] / dist, d[1] / dist, d[2] / dist};
        for (int i = 0; i < 3; i++) {
            h[i] = u[i];
            h[TH0 + i] = u[0] * M[0][i] + u[1] * M[1][i] + u[2] * M[2][i];
        }
        for (Py_ssize_t j = 0; j < n_lever; j++)
            h[lc[j]] = u[0] * R[0][j] + u[1] * R[1][j] + u[2] * R[2][j];
        double model = dist;
        PyObject *cols = PyTuple_GET_ITEM(columns, a);
        if (!PyTuple_Check(cols)) {
            PyErr_SetString(PyExc_TypeError, COLUMNS_TYPE);
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
