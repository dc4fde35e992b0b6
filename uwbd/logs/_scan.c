/* uwbd.logs._scan: the per-message loops of reading a whole log, in C.
 *
 * uwbd.logs.scan reads a chunk's records with one struct call a message, and
 * uwbd.logs.mcaplog._read_whole turns each into a LogMessage: two Python loops over every
 * message of the file (a 10-minute log holds ~150 000), a sixth of a whole `uwbd replay`.
 * These are the same loops (the Python code stays the reference, and runs where this is not
 * built or UWBD_PURE_PYTHON is set):
 *
 *   chunk_messages(data, pos) -> ([(channel id, log time, payload)], stop)
 *       the run of message records of data (a chunk's records) from pos: stop is where the
 *       first other record starts (or len(data)); ValueError("ends mid-record" or
 *       "message length") where scan._chunk raises UnusualRecordError with that text
 *   log_messages(records, topics, raw_channels, decode_raw, LogMessage, out) -> None
 *       each (channel id, log time, data) as LogMessage(topic, log time, data) appended to
 *       out: the topic topics.get(channel, "?"); for a channel in raw_channels the bytes
 *       of its uwbd.Raw message (a one-byte length here, else decode_raw(data), the data
 *       kept as they are where that raises ValueError)
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

#include "../_tuple.h"

#define OP_MESSAGE 0x05
#define MESSAGE_FIXED 22 /* channel id u16, sequence u32, log time u64, publish time u64 */

static uint64_t le64(const unsigned char *b)
{
    uint64_t v = 0;
    for (int i = 7; i >= 0; i--)
        v = (v << 8) | b[i];
    return v;
}

static PyObject *chunk_messages(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 2 || !PyBytes_Check(args[0])) {
        PyErr_SetString(PyExc_TypeError, "chunk_messages(data: bytes, pos: int)");
        return NULL;
    }
    Py_ssize_t pos = PyLong_AsSsize_t(args[1]);
    if (pos == -1 && PyErr_Occurred())
        return NULL;
    const unsigned char *d = (const unsigned char *)PyBytes_AS_STRING(args[0]);
    Py_ssize_t end = PyBytes_GET_SIZE(args[0]);
    if (pos < 0 || pos > end) {
        PyErr_SetString(PyExc_ValueError, "position outside the data");
        return NULL;
    }
    PyObject *out = PyList_New(0);
    if (out == NULL)
        return NULL;
    while (pos < end) {
        if (end - pos < 9) {
            PyErr_SetString(PyExc_ValueError, "ends mid-record");
            goto fail;
        }
        int op = d[pos];
        uint64_t length = le64(d + pos + 1);
        if (op != OP_MESSAGE)
            break;
        Py_ssize_t start = pos + 9;
        if (length > (uint64_t)(end - start)) {
            PyErr_SetString(PyExc_ValueError, "ends mid-record");
            goto fail;
        }
        Py_ssize_t stop = start + (Py_ssize_t)length;
        if (length < MESSAGE_FIXED) {
            PyErr_SetString(PyExc_ValueError, "message length");
            goto fail;
        }
        unsigned channel = d[start] | (d[start + 1] << 8);
        PyObject *item = Py_BuildValue(
            "(IKy#)", channel, (unsigned long long)le64(d + start + 6),
            (const char *)(d + start + MESSAGE_FIXED), stop - start - MESSAGE_FIXED);
        if (item == NULL)
            goto fail;
        int rc = PyList_Append(out, item);
        Py_DECREF(item);
        if (rc < 0)
            goto fail;
        pos = stop;
    }
    return Py_BuildValue("(Nn)", out, pos);
fail:
    Py_DECREF(out);
    return NULL;
}

static PyObject *log_messages(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 6 || !PyList_Check(args[0]) || !PyDict_Check(args[1]) ||
        !PyAnySet_Check(args[2]) || !PyType_Check(args[4]) ||
        !PyType_IsSubtype((PyTypeObject *)args[4], &PyTuple_Type) || !PyList_Check(args[5])) {
        PyErr_SetString(PyExc_TypeError, "log_messages(records: list, topics: dict, "
                        "raw_channels: set, decode_raw, LogMessage, out: list)");
        return NULL;
    }
    PyObject *records = args[0], *topics = args[1], *raw = args[2], *decode_raw = args[3];
    PyTypeObject *type = (PyTypeObject *)args[4];
    PyObject *out = args[5], *unknown = PyUnicode_FromString("?");
    if (unknown == NULL)
        return NULL;
    for (Py_ssize_t i = 0; i < PyList_GET_SIZE(records); i++) {
        PyObject *rec = PyList_GET_ITEM(records, i);
        if (!PyTuple_Check(rec) || PyTuple_GET_SIZE(rec) != 3 ||
            !PyBytes_Check(PyTuple_GET_ITEM(rec, 2))) {
            PyErr_SetString(PyExc_TypeError, "a record: (channel id, log time, bytes)");
            goto fail;
        }
        Py_INCREF(rec); /* held: decode_raw is Python code */
        PyObject *channel = PyTuple_GET_ITEM(rec, 0), *data = PyTuple_GET_ITEM(rec, 2);
        int is_raw = PySet_Contains(raw, channel);
        if (is_raw < 0) {
            Py_DECREF(rec);
            goto fail;
        }
        Py_INCREF(data);
        if (is_raw) {
            const unsigned char *b = (const unsigned char *)PyBytes_AS_STRING(data);
            Py_ssize_t n = PyBytes_GET_SIZE(data);
            PyObject *inner;
            if (n >= 2 && b[0] == 0x0A && b[1] == n - 2 && b[1] < 0x80) {
                inner = PyBytes_FromStringAndSize((const char *)b + 2, n - 2);
            } else {
                inner = PyObject_CallOneArg(decode_raw, data);
                if (inner == NULL && PyErr_ExceptionMatches(PyExc_ValueError)) {
                    PyErr_Clear(); /* not one: left as it is */
                    inner = Py_NewRef(data);
                }
            }
            Py_DECREF(data);
            if (inner == NULL) {
                Py_DECREF(rec);
                goto fail;
            }
            data = inner;
        }
        PyObject *topic = PyDict_GetItemWithError(topics, channel); /* after decode_raw */
        if (topic == NULL && PyErr_Occurred()) {
            Py_DECREF(data);
            Py_DECREF(rec);
            goto fail;
        }
        PyObject *items[3] = {Py_NewRef(topic != NULL ? topic : unknown),
                              Py_NewRef(PyTuple_GET_ITEM(rec, 1)), data};
        Py_DECREF(rec);
        PyObject *message = uwbd_tuple_of(type, items, 3);
        if (message == NULL)
            goto fail;
        int rc = PyList_Append(out, message);
        Py_DECREF(message);
        if (rc < 0)
            goto fail;
    }
    Py_DECREF(unknown);
    Py_RETURN_NONE;
fail:
    Py_DECREF(unknown);
    return NULL;
}

static PyMethodDef scan_methods[] = {
    {"chunk_messages", (PyCFunction)(void (*)(void))chunk_messages, METH_FASTCALL,
     "The run of message records of a chunk's data from pos: ([...], stop)."},
    {"log_messages", (PyCFunction)(void (*)(void))log_messages, METH_FASTCALL,
     "Records as LogMessage(topic, log time, data), appended to out."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef scan_module = {
    PyModuleDef_HEAD_INIT, "_scan", "The per-message loops of reading a whole log.", -1,
    scan_methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__scan(void) { return PyModule_Create(&scan_module); }
