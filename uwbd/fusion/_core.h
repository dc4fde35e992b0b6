/* What the C core's files share (_core.c: the filter's algebra; _imu_read.c: the common IMU
 * read in one call). */
#ifndef UWBD_CORE_H
#define UWBD_CORE_H

#include <Python.h>

#define N_CORE 15

/* Three (or four) floats out of a list or tuple of floats. */
int uwbd_get_vec(PyObject *seq, double *out, Py_ssize_t n, const char *what);
/* A new list (as_list) or tuple of n floats; NULL with an error set. */
PyObject *uwbd_floats(const double *v, Py_ssize_t n, int as_list);
/* Store doubles back into an existing list of that length, in place. */
int uwbd_set_list(PyObject *list, const double *v, Py_ssize_t n);
/* Eskf.predict's arithmetic: p, v, sum_fn, sum_w in place, the new q in qn. */
void uwbd_predict_step(double p[3], double v[3], const double q[4], const double bg[3],
                       const double ba[3], double sfn[3], double sw[3], const double acc[3],
                       const double gyro[3], double dt, double g, double qn[4]);

/* _imu_read.c */
int uwbd_imu_read_init(void);
PyObject *uwbd_imu_read(PyObject *self, PyObject *const *args, Py_ssize_t nargs);
PyObject *uwbd_imu_step(PyObject *self, PyObject *const *args, Py_ssize_t nargs);

/* _outcomes.c */
int uwbd_outcomes_init(void);
PyObject *uwbd_outcomes(PyObject *self, PyObject *const *args, Py_ssize_t nargs);

#endif
