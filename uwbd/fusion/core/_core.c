/* uwbd.fusion.core._core: the filter's numbers in C. The State type (_state.c) owns the error-state
 * EKF's nominal state, covariance and interval sums in its own memory, behind a few typed
 * operations, each a step of docs/ekf.md; beside it, the stateless multilateration (_lsq.c)
 * and the rest test's moments (_rest.c). Policy (phases, gates, health, recovery) is
 * Python's: nothing here reads a Python object's attributes.
 *
 * The reference is the pure-Python code (uwbd/fusion/core/eskf.py, lsq.py, rest.py), which
 * UWBD_PURE_PYTHON=1 runs instead; tests/test_core.py compares the two. Built by the
 * package's own build (setup.py) with -ffp-contract=off, so that `a * b + c` rounds as
 * Python rounds it. Matrices arrive through the buffer protocol (C-contiguous float64): no
 * numpy headers are needed to build. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>

#include "_core.h"

/* -- helpers ---------------------------------------------------------------------------- */

int uwbd_get_doubles(PyObject *obj, Py_buffer *view, Py_ssize_t count, int writable,
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

void uwbd_turned(const double q[4], double tx, double ty, double tz, double out[4])
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

void uwbd_quat_to_matrix(const double q[4], double R[3][3])
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

void uwbd_transform_attitude(double *P, Py_ssize_t n, const double G[3][3])
{
    for (Py_ssize_t b = 0; b < n; b++) {
        double c0 = P[TH0 * n + b], c1 = P[(TH0 + 1) * n + b], c2 = P[(TH0 + 2) * n + b];
        for (int i = 0; i < 3; i++)
            P[(TH0 + i) * n + b] = G[i][0] * c0 + G[i][1] * c1 + G[i][2] * c2;
    }
    for (Py_ssize_t a = 0; a < n; a++) {
        double *row = P + a * n + TH0;
        double c0 = row[0], c1 = row[1], c2 = row[2];
        for (int i = 0; i < 3; i++)
            row[i] = c0 * G[i][0] + c1 * G[i][1] + c2 * G[i][2];
    }
}

void uwbd_symmetrise(double *P, Py_ssize_t n)
{
    for (Py_ssize_t i = 0; i < n; i++)
        for (Py_ssize_t j = i + 1; j < n; j++)
            P[i * n + j] = P[j * n + i] = 0.5 * (P[i * n + j] + P[j * n + i]);
}

/* -- the module ------------------------------------------------------------------------- */

static PyMethodDef core_methods[] = {
    {"gauss_newton", (PyCFunction)(void (*)(void))uwbd_gauss_newton, METH_FASTCALL,
     "lsq._solve's Gauss-Newton iteration, in place on x; the iterations, 0: no fix."},
    {"leverages", (PyCFunction)(void (*)(void))uwbd_leverages, METH_FASTCALL,
     "Each range's leverage at x (multilaterate's outlier test); None if singular."},
    {"window_moments", (PyCFunction)(void (*)(void))uwbd_window_moments, METH_FASTCALL,
     "ImuWindow._judge's mean and std of the six axes over the last span_ns, or None."},
    {"snapshot_gain", (PyCFunction)(void (*)(void))uwbd_snapshot_gain, METH_FASTCALL,
     "bias_gain.snapshot_gain: one snapshot's gain of a position offset, or None."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef core_module = {
    PyModuleDef_HEAD_INIT, "_core",
    "The filter's numbers in C: the State type, the IMU front and the UWB-only "
    "multilateration (uwbd/fusion/core/eskf.py, checks/imu_check.py, lsq.py: the reference).", -1,
    core_methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__core(void)
{
    if (PyType_Ready(&UwbdStateType) < 0 || uwbd_imu_front_ready() < 0)
        return NULL;
    PyObject *module = PyModule_Create(&core_module);
    if (module == NULL)
        return NULL;
    if (PyModule_AddObjectRef(module, "State", (PyObject *)&UwbdStateType) < 0 ||
        PyModule_AddObjectRef(module, "ImuFront", (PyObject *)&UwbdImuFrontType) < 0) {
        Py_DECREF(module);
        return NULL;
    }
    return module;
}
