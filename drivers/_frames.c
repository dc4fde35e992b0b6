/* drivers._frames: the common Nooploop read (one whole TagFrame0) as one call; the
 * WitMotion stream parser is _wit.c's WitStream.
 *
 * A Nooploop tag sends a 128-byte TagFrame0 ten times a second and a read almost always
 * holds exactly one. In Python, NlinkParser.feed scans it, decodes every field through the
 * layout table and makes the ranges' and the epoch's dataclasses (~18 µs); this checks the
 * frame (header, function mark, checksum) and makes the same UwbRanges from the fields the
 * parser keeps, each object's slots set by their descriptors as the dataclasses' own
 * __init__ sets them. It declines (None) for anything else, which the Python parser, the
 * reference, then takes.
 *
 *   tag_frame0(data, t_ns, parts) -> UwbRanges | None
 * parts = (UwbRanges, its slot descriptors (8), AnchorRange, its slot descriptors (6)),
 * made by drivers.nlink from the dataclasses' fields, in their order.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>
#include <structmember.h>

#include "_wit.h"

#define FRAME_LEN 128
#define N_SLOTS 8
/* TagFrame0's offsets (drivers/nlink.py TAG_FRAME0, docs/wire-formats.md) */
#define OFF_ID 2
#define OFF_POS 4
#define OFF_VEL 13
#define OFF_DIS 22
#define OFF_SYSTEM_TIME 112
#define OFF_EOP 117
enum { UWB_FIELDS = 8, RANGE_FIELDS = 6 };

static long i24(const unsigned char *b)
{
    long v = (long)b[0] | ((long)b[1] << 8) | ((long)b[2] << 16);
    return v & 0x800000 ? v - 0x1000000 : v;
}

/* An instance of a slots dataclass, its fields set by their descriptors (values stolen) */
PyObject *drivers_make(PyObject *type, PyObject *fields, PyObject **values, int n)
{
    PyObject *obj = NULL;
    for (int i = 0; i < n; i++)
        if (values[i] == NULL)
            goto done;
    obj = ((PyTypeObject *)type)->tp_alloc((PyTypeObject *)type, 0);
    for (int i = 0; i < n && obj != NULL; i++) {
        PyObject *descr = PyTuple_GET_ITEM(fields, i);
        descrsetfunc set = Py_TYPE(descr)->tp_descr_set;
        if (set == NULL || set(descr, obj, values[i]) < 0) {
            if (!PyErr_Occurred())
                PyErr_SetString(PyExc_TypeError, "drivers._frames: a field is no slot");
            Py_CLEAR(obj);
        }
    }
done:
    for (int i = 0; i < n; i++)
        Py_XDECREF(values[i]);
    return obj;
}

/* (a / div, b / div, c / div) of three fields of `size` bytes (3: i24, 1: u8) */
static PyObject *triple(const unsigned char *b, int size, double div)
{
    double v[3];
    for (int i = 0; i < 3; i++)
        v[i] = (double)(size == 3 ? i24(b + 3 * i) : (long)b[i]) / div;
    return Py_BuildValue("(ddd)", v[0], v[1], v[2]);
}

static PyObject *tag_frame0(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 3 || !PyTuple_Check(args[2]) || PyTuple_GET_SIZE(args[2]) != 4) {
        PyErr_SetString(PyExc_TypeError, "tag_frame0(data, t_ns, parts)");
        return NULL;
    }
    PyObject *uwb_type = PyTuple_GET_ITEM(args[2], 0), *uwb_fields = PyTuple_GET_ITEM(args[2], 1);
    PyObject *range_type = PyTuple_GET_ITEM(args[2], 2);
    PyObject *range_fields = PyTuple_GET_ITEM(args[2], 3);
    if (!PyType_Check(uwb_type) || !PyType_Check(range_type) || !PyTuple_Check(uwb_fields) ||
        PyTuple_GET_SIZE(uwb_fields) != UWB_FIELDS || !PyTuple_Check(range_fields) ||
        PyTuple_GET_SIZE(range_fields) != RANGE_FIELDS) {
        PyErr_SetString(PyExc_TypeError, "tag_frame0: parts (UwbRanges, 8 slots, "
                        "AnchorRange, 6 slots) expected");
        return NULL;
    }
    Py_buffer view;
    if (PyObject_GetBuffer(args[0], &view, PyBUF_SIMPLE) < 0)
        return NULL;
    const unsigned char *b = view.buf;
    unsigned sum = 0;
    if (view.len == FRAME_LEN && b[0] == 0x55 && b[1] == 0x01)
        for (int i = 0; i < FRAME_LEN - 1; i++)
            sum += b[i];
    if (view.len != FRAME_LEN || b[0] != 0x55 || b[1] != 0x01 ||
        (sum & 0xFF) != b[FRAME_LEN - 1]) {
        PyBuffer_Release(&view);
        Py_RETURN_NONE; /* not one whole TagFrame0: the parser's own scan says what it is */
    }
    PyObject *ranges = PyList_New(0), *out = NULL;
    for (int k = 0; k < N_SLOTS && ranges != NULL; k++) {
        double d = (double)i24(b + OFF_DIS + 3 * k) / 1000.0;
        if (d == 0.0)
            continue; /* 0 is "no range" */
        PyObject *values[RANGE_FIELDS] = {PyLong_FromLong(k), PyFloat_FromDouble(d),
                                          Py_NewRef(Py_None), Py_NewRef(Py_None),
                                          Py_NewRef(Py_None), Py_NewRef(Py_None)};
        PyObject *r = drivers_make(range_type, range_fields, values, RANGE_FIELDS);
        if (r == NULL || PyList_Append(ranges, r) < 0)
            Py_CLEAR(ranges);
        Py_XDECREF(r);
    }
    if (ranges != NULL) {
        uint32_t ms = (uint32_t)b[OFF_SYSTEM_TIME] | ((uint32_t)b[OFF_SYSTEM_TIME + 1] << 8) |
                      ((uint32_t)b[OFF_SYSTEM_TIME + 2] << 16) |
                      ((uint32_t)b[OFF_SYSTEM_TIME + 3] << 24);
        /* t_ns, ranges, tag_position_m, quality, tag_velocity_mps, tag_position_error_m,
         * tag_id, device_time_ms */
        PyObject *values[UWB_FIELDS] = {
            Py_NewRef(args[1]), PyList_AsTuple(ranges), triple(b + OFF_POS, 3, 1000.0),
            Py_NewRef(Py_None), triple(b + OFF_VEL, 3, 10000.0), triple(b + OFF_EOP, 1, 100.0),
            PyLong_FromLong(b[OFF_ID]), PyLong_FromUnsignedLong(ms)};
        Py_DECREF(ranges);
        out = drivers_make(uwb_type, uwb_fields, values, UWB_FIELDS);
    }
    PyBuffer_Release(&view);
    return out;
}

/* retimed(frame, t_ns) -> the frame (an instance of a slots dataclass of its own, with a
 * t_ns field) with t_ns set: what dataclasses.replace(frame, t_ns=t_ns) makes, each slot
 * taken over as it is, without the frozen __init__'s setattr per field (~10 µs a frame
 * there). The pipeline re-times every sample of a read of several (drivers.frames). */
static PyObject *retimed(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 2 || !PyLong_Check(args[1])) {
        PyErr_SetString(PyExc_TypeError, "retimed(frame, t_ns: int)");
        return NULL;
    }
    PyTypeObject *type = Py_TYPE(args[0]);
    PyMemberDef *members = type->tp_members;
    if (members == NULL || type->tp_base != &PyBaseObject_Type || type->tp_dictoffset != 0) {
        PyErr_SetString(PyExc_TypeError, "retimed: a slots dataclass of its own is needed");
        return NULL;
    }
    int found = 0;
    for (PyMemberDef *m = members; m->name != NULL; m++) {
        if (m->type != T_OBJECT_EX) {
            PyErr_SetString(PyExc_TypeError, "retimed: every field must be a slot");
            return NULL;
        }
        found += strcmp(m->name, "t_ns") == 0;
    }
    if (!found) {
        PyErr_SetString(PyExc_TypeError, "retimed: the frame has no t_ns");
        return NULL;
    }
    PyObject *copy = type->tp_alloc(type, 0);
    if (copy == NULL)
        return NULL;
    for (PyMemberDef *m = members; m->name != NULL; m++) {
        PyObject *value = strcmp(m->name, "t_ns") == 0
                              ? args[1] : *(PyObject **)((char *)args[0] + m->offset);
        Py_XINCREF(value);
        *(PyObject **)((char *)copy + m->offset) = value;
    }
    return copy;
}

static PyMethodDef frames_methods[] = {
    {"retimed", (PyCFunction)(void (*)(void))retimed, METH_FASTCALL,
     "The frame (a slots dataclass) with t_ns set: dataclasses.replace(frame, t_ns=t_ns)."},
    {"tag_frame0", (PyCFunction)(void (*)(void))tag_frame0, METH_FASTCALL,
     "One whole Nooploop TagFrame0 as UwbRanges, or None (the parser takes it)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef frames_module = {
    PyModuleDef_HEAD_INIT, "_frames", "The drivers' C parsers: WitMotion's stream, the common Nooploop read.", -1,
    frames_methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__frames(void)
{
    if (PyType_Ready(&WitStreamType) < 0)
        return NULL;
    PyObject *m = PyModule_Create(&frames_module);
    if (m != NULL && PyModule_AddObjectRef(m, "WitStream", (PyObject *)&WitStreamType) < 0)
        Py_CLEAR(m);
    return m;
}
