/* What the C core's files share (_core.c: the filter's algebra; _imu_read.c: the common IMU
 * read in one call; _epoch.c: the common UWB message; _outcomes.c: its rows' outcomes). */
#ifndef UWBD_CORE_H
#define UWBD_CORE_H

#include <Python.h>
#include <stdint.h>

#define N_CORE 15

/* Three (or four) floats out of a list or tuple of floats. */
int uwbd_get_vec(PyObject *seq, double *out, Py_ssize_t n, const char *what);
/* A new list (as_list) or tuple of n floats; NULL with an error set. */
PyObject *uwbd_floats(const double *v, Py_ssize_t n, int as_list);
/* n floats out of a list (or, unless list_only, a tuple) of exactly n Python floats: 1, else
 * 0 (the callers decline). */
int uwbd_floats_of(PyObject *seq, double *out, Py_ssize_t n, int list_only);
/* The first n numbers of a tuple as doubles: 0, or -1 with an error set. */
int uwbd_doubles_of(PyObject *tuple, double *out, Py_ssize_t n);
/* Each of the n names interned: 0, or -1 with an error set. */
int uwbd_intern(const char *const *text, PyObject **out, int n);
/* Store doubles back into an existing list of that length, in place. */
int uwbd_set_list(PyObject *list, const double *v, Py_ssize_t n);
/* Eskf.predict's arithmetic: p, v, sum_fn, sum_w in place, the new q in qn. */
void uwbd_predict_step(double p[3], double v[3], const double q[4], const double bg[3],
                       const double ba[3], double sfn[3], double sw[3], const double acc[3],
                       const double gyro[3], double dt, double g, double qn[4]);

/* fuse_ranges on the epoch's own numbers (anchors k×3, ranges, var), nominal = p, v, q,
 * b_g, b_a: (rows, q), None (the reference's case), or NULL with an error set. */
PyObject *uwbd_fuse_ranges_on(PyObject *P_obj, PyObject *dx_obj, PyObject *b_r_obj,
                              PyObject *const *nominal, const double lever[3],
                              const double *anchors, const double *ranges, const double *var,
                              Py_ssize_t k, PyObject *columns, PyObject *H_obj,
                              PyObject *y_obj, PyObject *R_obj, PyObject *decide,
                              Py_ssize_t c0, Py_ssize_t c1);
/* A variance of P above its limit or below zero: 1, 0, -1 (an error). */
int uwbd_diagonal_out_of_bounds(PyObject *P_obj, PyObject *limit);
/* Every entry of P finite and below `bound` in magnitude: 1, 0, -1 (an error). */
int uwbd_all_finite_below(PyObject *P_obj, double bound);

/* pose_numbers(P, q, p, v, aligned, max_yaw_sigma): Filter.pose's numbers, or None. */
PyObject *uwbd_pose_numbers(PyObject *self, PyObject *const *args, Py_ssize_t nargs);

/* The running Eskf's nominal state as Eskf.predict reads and writes it (its namespace's
 * p, v, q, b_g, b_a, _sum_fn, _sum_w: new references; their numbers; gravity; _T). */
typedef struct {
    PyObject *lists[7];
    double st[7][4], gravity, interval;
} UwbdNominal;
int uwbd_nominal_init(void);
/* Read from the Eskf's namespace: 1 as expected (lists of floats, q a list or tuple;
 * floats), 0 not (decline), -1 an error. */
int uwbd_nominal_read(PyObject *ns, UwbdNominal *s);
/* Eskf.predict on it (p, v and the sums in place, q and _T stored anew): 0, or -1 with an
 * error set; *interval: _T now. */
int uwbd_nominal_predict(UwbdNominal *s, PyObject *ns, const double acc[3],
                         const double gyro[3], double dt, double *interval);
void uwbd_nominal_release(UwbdNominal *s);
/* Eskf.propagate on vars(ekf), without its Python call, where the C core runs it whole
 * (no Gauss–Markov state): 1 done, 0 not so (nothing changed: call the method), -1 an
 * error. */
int uwbd_propagate(PyObject *ns);

/* _imu_read.c */
/* An int within ±2^62 (1), None (1 and *none set, if none is given), else 0; -1 an error. */
int uwbd_as_i64(PyObject *v, int64_t *out, int *none);
int uwbd_imu_read_init(void);
PyObject *uwbd_imu_read(PyObject *self, PyObject *const *args, Py_ssize_t nargs);
PyObject *uwbd_imu_step(PyObject *self, PyObject *const *args, Py_ssize_t nargs);

/* _epoch.c */
int uwbd_epoch_init(void);
PyObject *uwbd_epoch_step(PyObject *self, PyObject *const *args, Py_ssize_t nargs);

/* _pose.c */
int uwbd_pose_init(void);
PyObject *uwbd_pose_step(PyObject *self, PyObject *const *args, Py_ssize_t nargs);

/* _outcomes.c */
int uwbd_outcomes_init(void);
PyObject *uwbd_outcomes(PyObject *self, PyObject *const *args, Py_ssize_t nargs);

#endif
