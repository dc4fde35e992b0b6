/* What the files of drivers._frames share */
#ifndef DRIVERS_WIT_H
#define DRIVERS_WIT_H
#include <Python.h>
extern PyTypeObject WitStreamType; /* _wit.c */
/* An instance of a slots dataclass, its n fields set by their descriptors (`fields`, in
 * order) as its __init__ sets them; the values are stolen (_frames.c). */
PyObject *drivers_make(PyObject *type, PyObject *fields, PyObject **values, int n);
#endif
