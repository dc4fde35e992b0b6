/* The Gauss–Newton multilateration's numbers for the UWB-only fixes: the iteration and each
 * range's leverage, stateless functions of the C core. Which range is an outlier, and what
 * then, is lsq.multilaterate's decision (Python only); its numpy kernels are the reference
 * tests/test_core.py holds these to. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>

#include "_core.h"

#define get_doubles uwbd_get_doubles

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

/* Σ (|x − a_i| − r_i)² over k anchors and ranges */
static double sum_squares(const double *anchors, const double *ranges, Py_ssize_t k,
                          const double x[3])
{
    double total = 0.0;
    for (Py_ssize_t a = 0; a < k; a++) {
        double dx = x[0] - anchors[3 * a], dy = x[1] - anchors[3 * a + 1],
               dz = x[2] - anchors[3 * a + 2];
        double r = sqrt(dx * dx + dy * dy + dz * dz) - ranges[a];
        total += r * r;
    }
    return total;
}

/* lsq._solve's iteration (see gauss_newton below) on k anchors and ranges, x in place;
 * the iterations, or 0 for no fix; out (3×3) the last step's (JᵀJ)⁻¹ when there is one. */
static long iterate(const double *anchors, const double *ranges, Py_ssize_t k, double x[3],
                    int dims, long max_iter, long max_halvings, double converged,
                    double accept_last, double *out)
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
        /* convergence is judged on the full step (a search cut short has not converged);
         * the step taken is halved while it raises the squares (lsq.MAX_HALVINGS times at
         * most) */
        double norm = 0.0;
        for (int i = 0; i < dims; i++)
            norm += step[i] * step[i];
        norm = sqrt(norm);
        double before = sum_squares(anchors, ranges, k, x), trial[3] = {x[0], x[1], x[2]};
        for (int h = 0;; h++) {
            for (int i = 0; i < dims; i++)
                trial[i] = x[i] + step[i];
            if (h == max_halvings || !(sum_squares(anchors, ranges, k, trial) > before))
                break;
            for (int i = 0; i < dims; i++)
                step[i] *= 0.5;
        }
        for (int i = 0; i < dims; i++)
            x[i] = trial[i];
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
 *              max_halvings, converged_m, accept_last_m, out (3×3)) -> iterations, or 0
 * lsq._solve's iteration: steps (JᵀJ) δ = −Jᵀ r on the first `dims` coordinates, each
 * halved while it raises the squares (max_halvings times at most), until a full
 * step is below converged_m; after max_iterations a last step above accept_last_m is no
 * fix; a range from an anchor closer than 1 µm or a singular JᵀJ is no fix either. `out`
 * gets (JᵀJ)⁻¹ of the last step in its top-left dims×dims, the rest zero: the fix's
 * covariance over σ². */
PyObject *uwbd_gauss_newton(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 9) {
        PyErr_SetString(PyExc_TypeError, "gauss_newton takes 9 arguments");
        return NULL;
    }
    long dims = PyLong_AsLong(args[3]);
    if (dims == -1 && PyErr_Occurred())
        return NULL;
    long max_iter = PyLong_AsLong(args[4]);
    if (max_iter == -1 && PyErr_Occurred())
        return NULL;
    long max_halvings = PyLong_AsLong(args[5]);
    if (max_halvings == -1 && PyErr_Occurred())
        return NULL;
    double converged = PyFloat_AsDouble(args[6]);
    if (converged == -1.0 && PyErr_Occurred())
        return NULL;
    double accept_last = PyFloat_AsDouble(args[7]);
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
    if (max_halvings < 0) {
        PyErr_SetString(PyExc_ValueError, "max_halvings must not be negative");
        return NULL;
    }
    if (get_doubles(args[8], &ob, 9, 1, "out") < 0)
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
                          (double *)xb.buf, (int)dims, max_iter, max_halvings, converged,
                          accept_last,
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
PyObject *uwbd_leverages(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
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


