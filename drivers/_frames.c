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

#define N_SLOTS 8
enum { UWB_FIELDS = 8, RANGE_FIELDS = 6 };

/* TagFrame0's layout, as drivers/nlink.py hands it from TAG_FRAME0 (the one table): the
 * frame's size, its header and mark bytes, the offsets of id, pos_m, vel_mps, dis_m,
 * system_time_ms and eop_m, and the divisors of pos_m, vel_mps, dis_m and eop_m. */
enum { TAG0_INTS = 9, TAG0_DIVS = 4 };
typedef struct {
    Py_ssize_t size, header, mark, id, pos, vel, dis, system_time, eop;
    double pos_div, vel_div, dis_div, eop_div;
} Tag0Layout;

static int tag0_layout(PyObject *numbers, Tag0Layout *l)
{
    static PyObject *seen; /* the tuple last read (the same object every call) */
    static Tag0Layout cached;
    if (numbers == seen) {
        *l = cached;
        return 0;
    }
    if (!PyTuple_Check(numbers) || PyTuple_GET_SIZE(numbers) != TAG0_INTS + TAG0_DIVS) {
        PyErr_SetString(PyExc_TypeError, "tag_frame0: the layout is 9 integers, 4 divisors");
        return -1;
    }
    Py_ssize_t at[TAG0_INTS];
    double div[TAG0_DIVS];
    for (int i = 0; i < TAG0_INTS; i++)
        if ((at[i] = PyLong_AsSsize_t(PyTuple_GET_ITEM(numbers, i))) == -1 && PyErr_Occurred())
            return -1;
    for (int i = 0; i < TAG0_DIVS; i++)
        if ((div[i] = PyFloat_AsDouble(PyTuple_GET_ITEM(numbers, TAG0_INTS + i))) == -1.0 &&
            PyErr_Occurred())
            return -1;
    Tag0Layout got = {at[0], at[1], at[2], at[3], at[4], at[5], at[6], at[7], at[8],
                      div[0], div[1], div[2], div[3]};
    for (int i = 3; i < TAG0_INTS; i++)
        if (at[i] < 2) {
            PyErr_SetString(PyExc_ValueError, "tag_frame0: an offset inside the header");
            return -1;
        }
    for (int i = 0; i < TAG0_DIVS; i++)
        if (!(div[i] > 0.0)) {
            PyErr_SetString(PyExc_ValueError, "tag_frame0: a divisor not positive");
            return -1;
        }
    if (got.size < 3 || got.id >= got.size || got.dis + 3 * N_SLOTS > got.size ||
        got.system_time + 4 > got.size ||
        got.eop + 3 > got.size || got.pos + 9 > got.size || got.vel + 9 > got.size) {
        PyErr_SetString(PyExc_ValueError, "tag_frame0: a field beyond the frame");
        return -1;
    }
    Py_XSETREF(seen, Py_NewRef(numbers));
    cached = *l = got;
    return 0;
}

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
    Tag0Layout l;
    if (nargs != 3 || !PyTuple_Check(args[2]) || PyTuple_GET_SIZE(args[2]) != 5) {
        PyErr_SetString(PyExc_TypeError, "tag_frame0(data, t_ns, parts)");
        return NULL;
    }
    if (tag0_layout(PyTuple_GET_ITEM(args[2], 4), &l) < 0)
        return NULL;
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
    int whole = view.len == l.size && b[0] == l.header && b[1] == l.mark;
    if (whole)
        for (Py_ssize_t i = 0; i < l.size - 1; i++)
            sum += b[i];
    if (!whole || (sum & 0xFF) != b[l.size - 1]) {
        PyBuffer_Release(&view);
        Py_RETURN_NONE; /* not one whole TagFrame0: the parser's own scan says what it is */
    }
    PyObject *ranges = PyList_New(0), *out = NULL;
    for (int k = 0; k < N_SLOTS && ranges != NULL; k++) {
        double d = (double)i24(b + l.dis + 3 * k) / l.dis_div;
        if (d == 0.0)
            continue; /* 0 is "no range" */
        /* anchor_id, range_m, then the fields the frame does not carry (nlink._FILLS) */
        PyObject *values[RANGE_FIELDS] = {PyLong_FromLong(k), PyFloat_FromDouble(d),
                                          Py_NewRef(Py_None), Py_NewRef(Py_None),
                                          Py_NewRef(Py_None), Py_NewRef(Py_None)};
        PyObject *r = drivers_make(range_type, range_fields, values, RANGE_FIELDS);
        if (r == NULL || PyList_Append(ranges, r) < 0)
            Py_CLEAR(ranges);
        Py_XDECREF(r);
    }
    if (ranges != NULL) {
        const unsigned char *st = b + l.system_time;
        uint32_t ms = (uint32_t)st[0] | ((uint32_t)st[1] << 8) | ((uint32_t)st[2] << 16) |
                      ((uint32_t)st[3] << 24);
        /* in the order nlink._FILLS names: t_ns, ranges, tag_position_m, quality,
         * tag_velocity_mps, tag_position_error_m, tag_id, device_time_ms */
        PyObject *values[UWB_FIELDS] = {
            Py_NewRef(args[1]), PyList_AsTuple(ranges), triple(b + l.pos, 3, l.pos_div),
            Py_NewRef(Py_None), triple(b + l.vel, 3, l.vel_div), triple(b + l.eop, 1, l.eop_div),
            PyLong_FromLong(b[l.id]), PyLong_FromUnsignedLong(ms)};
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
