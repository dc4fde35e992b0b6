/* A named tuple made from C (uwbd/logs/_scan.c, uwbd/fusion/core/_checks.c). */
#ifndef UWBD_TUPLE_H
#define UWBD_TUPLE_H

#include <Python.h>

/* A tuple of the tuple subclass `type` (a NamedTuple) holding the n items (new references,
 * stolen; a NULL among them: an error is set, NULL returned), as tuple.__new__(type, items)
 * makes it. Up to Python 3.13 a tuple's own allocation does that at a tenth of the cost;
 * from 3.14 a tuple caches its hash, which only the tuple constructor sets up. */
static inline PyObject *uwbd_tuple_of(PyTypeObject *type, PyObject **items, Py_ssize_t n)
{
    PyObject *out = NULL;
    for (Py_ssize_t i = 0; i < n; i++)
        if (items[i] == NULL)
            goto done;
#if PY_VERSION_HEX < 0x030E0000
    out = type->tp_alloc(type, n);
    if (out != NULL) {
        for (Py_ssize_t i = 0; i < n; i++)
            PyTuple_SET_ITEM(out, i, items[i]);
        return out;
    }
#else
    PyObject *plain = PyTuple_New(n);
    if (plain != NULL) {
        for (Py_ssize_t i = 0; i < n; i++)
            PyTuple_SET_ITEM(plain, i, items[i]);
        PyObject *args = PyTuple_Pack(1, plain);
        Py_DECREF(plain);
        if (args != NULL) {
            out = PyTuple_Type.tp_new(type, args, NULL);
            Py_DECREF(args);
        }
        return out;
    }
#endif
done:
    for (Py_ssize_t i = 0; i < n; i++)
        Py_XDECREF(items[i]);
    return out;
}

#endif
