/* The rest test's moments over the IMU window (uwbd/fusion/policy/rest.py is the reference): a
 * stateless function of the C core. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>

#include "_core.h"


/* window_moments(samples, span_ns) -> (mean, std) of the six axes over the rows of the last
 * span_ns, or None for fewer than 3 rows: ImuWindow._judge's numpy steps, to the bit. The
 * rows are (t_ns, ax, ay, az, gx, gy, gz) tuples in time order (a deque); numpy takes the
 * times as float64 (np.array of the rows), finds the first row at or after last - span_ns
 * (searchsorted) and sums each axis over the rows in order (a reduction along axis 0 is a
 * running sum), divides by n, and the same for the squared deviations. */
PyObject *uwbd_window_moments(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
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

