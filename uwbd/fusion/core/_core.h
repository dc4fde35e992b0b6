/* What the C core's files share. _core.c: the module and its helpers; _state.c: the State
 * type, which owns the filter's numbers (docs/ekf.md §2, §3, §5); _update.c: the scalar
 * updates and the robust weights (§5); mm_range.c: the range rows (§4); _lsq.c: the UWB-only
 * multilateration; _rest.c: the rest test's moments; _checks.c: the installation checks'
 * numbers; _imu.c: the IMU front (screen, body
 * maps, the common sample integrated). No function here reads a Python
 * object's attributes: numbers come in as arguments, buffers or tuples of floats. */
#ifndef UWBD_CORE_H
#define UWBD_CORE_H

#include <Python.h>
#include <stdint.h>

#include "_layout.h" /* N_CORE and the nominal state's offsets, generated from layout.py */
#define TH0 6     /* the attitude error's first column */

/* -- helpers (_core.c) ------------------------------------------------------------------- */
/* A C-contiguous float64 buffer of `count` doubles (count < 0: any size): 0, or -1. */
int uwbd_get_doubles(PyObject *obj, Py_buffer *view, Py_ssize_t count, int writable,
                     const char *what);
/* n floats out of a sequence of numbers: 0, or -1 with an error set. */
int uwbd_get_vec(PyObject *seq, double *out, Py_ssize_t n, const char *what);
/* A new list (as_list) or tuple of n floats; NULL with an error set. */
PyObject *uwbd_floats(const double *v, Py_ssize_t n, int as_list);
/* q ⊗ Exp(θ), normalised (eskf._turned). */
void uwbd_turned(const double q[4], double tx, double ty, double tz, double out[4]);
/* R(q): body to navigation. */
void uwbd_quat_to_matrix(const double q[4], double R[3][3]);
/* P ← T P Tᵀ with T = I but its attitude block G (n×n, in place). */
void uwbd_transform_attitude(double *P, Py_ssize_t n, const double G[3][3]);
/* P ← (P + Pᵀ)/2, as numpy's 0.5 * (P + P.T) (n×n, in place). */
void uwbd_symmetrise(double *P, Py_ssize_t n);

/* -- the scalar updates (_update.c) ------------------------------------------------------ */
/* How each row of one update is weighed (robust.RowPolicy: a tuple, read once). */
typedef struct {
    const char *kinds;
    Py_ssize_t count;
    double gate_1, c_long, c_short;
    int robust, fix_ok;
} UwbdRowPolicy;
/* A RowPolicy tuple read into pol (1), a callable to call back per row (0), or -1. */
int uwbd_get_decide(PyObject *decide, UwbdRowPolicy *pol);
/* The rows of Eskf.sequential_update on P (n×n) and dx (n) in place; work: 3n doubles.
 * Returns the list of (ν, S, w, numerical) rows and in *fused whether any was fused; each
 * row's weight into weights (m, or NULL), 0 where it was not fused. */
PyObject *uwbd_scalar_rows(double *P, double *dx, Py_ssize_t n, const double *H,
                           const double *y, const double *Rv, Py_ssize_t m, PyObject *decide,
                           const UwbdRowPolicy *pol, Py_ssize_t c0, Py_ssize_t c1,
                           double *work, int *fused, double *weights);
/* The same rows on a sub-filter of the bank (P_k n×n, its offset e n, in place), each with
 * the weight the main filter gave it (weights; rows of weight 0 and rows of the anchor it
 * leaves out, row_anchor[i] == left_out, skipped); work: 3n doubles. */
void uwbd_bank_rows(double *P, double *e, Py_ssize_t n, const double *H, const double *y,
                    const double *Rv, Py_ssize_t m, const double *weights,
                    const long long *row_anchor, long long left_out, Py_ssize_t c0,
                    Py_ssize_t c1, double *work);

/* -- the range model's rows (mm_range.c) ------------------------------------------------ */
/* The rows of the ranges (measurements.range_rows) into H (k×n, zeroed) and y, each
 * antenna-anchor distance into dist (k): 0, or -1. */
int uwbd_range_rows(const double p[3], const double q[4], const double lever[3],
                    const double *anchors, const double *ranges, Py_ssize_t k,
                    const double *b_r, Py_ssize_t n, PyObject *columns,
                    PyObject *lever_columns, double *H, double *y, double *dist);
/* A range has a line to linearise: its antenna over 1 mm from its anchor (NaN: none). */
#define UWBD_LINE_OF(dist) ((dist) >= 1e-3)

/* -- the installation checks' numbers (_checks.c) ---------------------------------------- */
/* Baarda's single-fault estimates of k innovations nu with covariance S (k×k, destroyed):
 * b_j = (S⁻¹ν)_j / (S⁻¹)_jj, d_j = (S⁻¹)_jj; work: k×k. 0, or -1 when S is singular. */
int uwbd_single_faults(double *S, const double *nu, Py_ssize_t k, double *b, double *d,
                       double *work);

/* -- stateless functions of the module -------------------------------------------------- */
PyObject *uwbd_gauss_newton(PyObject *self, PyObject *const *args, Py_ssize_t nargs);
PyObject *uwbd_leverages(PyObject *self, PyObject *const *args, Py_ssize_t nargs);
PyObject *uwbd_window_moments(PyObject *self, PyObject *const *args, Py_ssize_t nargs);
PyObject *uwbd_snapshot_gain(PyObject *self, PyObject *const *args, Py_ssize_t nargs);

/* -- the State type (_state.c) ---------------------------------------------------------- */
extern PyTypeObject UwbdStateType;
/* The operations the IMU front (_imu.c) runs on a State without a Python call: predict
 * (§2, one sample in body axes), propagate (§3), and the time integrated since it. */
void uwbd_state_predict(PyObject *state, const double acc[3], const double gyro[3], double dt);
void uwbd_state_propagate(PyObject *state);
double uwbd_state_interval(PyObject *state);

/* -- the IMU front (_imu.c): each sample judged, mapped to body axes, integrated --------- */
extern PyTypeObject UwbdImuFrontType;
int uwbd_imu_front_ready(void); /* its constants made and the type readied: 0, or -1 */
/* One sample (sensor axes) through the front while it is the common one: later than *last
 * by at most max_gap_s and later than *state_ns. 0: judged good, mapped (body axes into
 * ab, gb), integrated into state (propagated when its interval reaches every_s), *last and
 * *state_ns its time; -1: not the common sample (not judged: the policy's); 1 + r: the
 * screen rejected it, for the reason uwbd_front_reason(front, 1 + r) (borrowed). */
int uwbd_front_step(PyObject *front, PyObject *state, long long t_ns, const double a[3],
                    const double g[3], long long *last, long long *state_ns, double max_gap,
                    double every, double ab[3], double gb[3]);
PyObject *uwbd_front_reason(PyObject *front, int r);
/* One (t_ns, acc, gyro) tuple through uwbd_front_step, its row (t_ns, acc_b..., gyro_b...)
 * appended to rows when integrated: as uwbd_front_step, or -2 with an error set. */
int uwbd_front_take(PyObject *front, PyObject *state, PyObject *sample, long long *last,
                    long long *state_ns, double max_gap, double every, PyObject *rows,
                    double ab[3], double gb[3]);

#endif
