/* uwbd.logs._records: the output log's most common records, written in C.
 *
 * At 200 Hz the IMU's reads are two thirds of a log's records: each brings its /raw/<source>
 * record and its /imu record. uwbd.logs.mcaplog.LogWriter.read writes both through
 * LogWriter.raw and LogWriter.frame (the JSON by orjson, the records by
 * uwbd.logs.chunked.ChunkedWriter.add_message): those stay the reference, and run where
 * this is not built or UWBD_PURE_PYTHON is set. This is the same work in one call:
 *
 *   imu_read(parts, raw_channel, imu_channel, t_ns, data, sample) -> 0, 1, 2 or 3
 *       parts: (vars(LogWriter), vars(ChunkedWriter), ImuSample, orjson.dumps)
 *       2: both records written, as LogWriter.raw(source, t_ns, data) and then
 *          LogWriter.frame(sample) write them (sequence numbers, the unflushed count, the
 *          chunk's bytes and its message index), byte for byte;
 *       3: the same, and the chunk is now over its size: the caller ends it (as
 *          add_message does);
 *       1: the /raw record written and the chunk is now over its size: the caller ends
 *          the chunk and writes the frame;
 *       0: declined before any write: anything but the common IMU sample (accelerometer and
 *          gyro as three floats each, perhaps a temperature, nothing else), a number not
 *          finite (orjson writes null), a time or channel the record cannot hold.
 *
 * The JSON is the reference's, byte for byte: compact, its keys in the same order, the
 * integers in decimal, the numbers of the vectors and the temperature as orjson writes them
 * (its dumps, in parts, makes them: its float writer is ten times Python's repr).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define OP_MESSAGE 0x05
#define MESSAGE_HEAD 31 /* opcode u8, length u64, channel u16, sequence u32, 2 x time u64 */
#define MESSAGE_FIXED 22 /* the record's content before its data */
#define JSON_MAX 512     /* the IMU record: ~110 fixed bytes, 3 integers, 7 floats */

static PyObject *s_t_ns, *s_acc, *s_gyro, *s_temp, *s_angle, *s_mag, *s_quat, *s_device,
    *s_sequence, *s_unflushed, *s_chunk, *s_index, *s_chunk_size;

/* ------------------------------------------------------------------ JSON, as orjson */

static char *put(char *p, const char *s)
{
    size_t n = strlen(s);
    memcpy(p, s, n);
    return p + n;
}

static char *put_u64(char *p, uint64_t v)
{
    char tmp[24];
    int n = 0;
    do {
        tmp[n++] = (char)('0' + v % 10);
        v /= 10;
    } while (v);
    while (n)
        *p++ = tmp[--n];
    return p;
}

/* The three floats of a tuple, when it is one of three finite floats. */
static int three_floats(PyObject *v, double out[3])
{
    if (!PyTuple_CheckExact(v) || PyTuple_GET_SIZE(v) != 3)
        return 0;
    for (int i = 0; i < 3; i++) {
        PyObject *item = PyTuple_GET_ITEM(v, i);
        if (!PyFloat_CheckExact(item))
            return 0;
        out[i] = PyFloat_AS_DOUBLE(item);
        if (!isfinite(out[i]))
            return 0;
    }
    return 1;
}

/* The JSON bytes of v by dumps (orjson's), appended; NULL with an error set. */
static char *put_json(char *p, const char *end, PyObject *dumps, PyObject *v)
{
    PyObject *text = PyObject_CallOneArg(dumps, v);
    if (text == NULL)
        return NULL;
    if (!PyBytes_Check(text) || PyBytes_GET_SIZE(text) > end - p) {
        PyErr_SetString(PyExc_ValueError, "imu_read: dumps gave no JSON bytes of the size expected");
        Py_DECREF(text);
        return NULL;
    }
    memcpy(p, PyBytes_AS_STRING(text), (size_t)PyBytes_GET_SIZE(text));
    p += PyBytes_GET_SIZE(text);
    Py_DECREF(text);
    return p;
}

/* ------------------------------------------------------------------ MCAP records */

static void le(unsigned char *b, uint64_t v, int n)
{
    for (int i = 0; i < n; i++, v >>= 8)
        b[i] = (unsigned char)(v & 0xFF);
}

/* A non-negative int below 2**63 (the log times), or -1 (no error left set). */
static long long time_of(PyObject *v)
{
    if (!PyLong_CheckExact(v))
        return -1;
    int overflow = 0;
    long long t = PyLong_AsLongLongAndOverflow(v, &overflow);
    if (t == -1 && PyErr_Occurred()) {
        PyErr_Clear();
        return -1;
    }
    return overflow ? -1 : t;
}

/* LogWriter._add then ChunkedWriter.add_message for one message: the sequence and the
 * unflushed count, the message index (log time, offset), the record into the chunk.
 * Returns the chunk's new size, or -1 with an error set. */
static Py_ssize_t add_message(PyObject *log, PyObject *writer, PyObject *channel,
                              unsigned channel_id, long long t_ns, const char *head,
                              Py_ssize_t head_size, const char *body, Py_ssize_t body_size)
{
    PyObject *seq_obj = PyDict_GetItemWithError(log, s_sequence);
    PyObject *unflushed_obj = PyDict_GetItemWithError(log, s_unflushed);
    PyObject *chunk = PyDict_GetItemWithError(writer, s_chunk);
    PyObject *index = PyDict_GetItemWithError(writer, s_index);
    if (seq_obj == NULL || unflushed_obj == NULL || chunk == NULL || index == NULL ||
        !PyByteArray_CheckExact(chunk) || !PyDict_CheckExact(index)) {
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_TypeError, "imu_read: the writers' state is not as expected");
        return -1;
    }
    unsigned long long seq = PyLong_AsUnsignedLongLongMask(seq_obj);
    long long unflushed = PyLong_AsLongLong(unflushed_obj);
    if (PyErr_Occurred())
        return -1;
    seq = (seq + 1) & 0xFFFFFFFFull;
    PyObject *seq_new = PyLong_FromUnsignedLongLong(seq);
    if (seq_new == NULL || PyDict_SetItem(log, s_sequence, seq_new) < 0) {
        Py_XDECREF(seq_new);
        return -1;
    }
    Py_DECREF(seq_new);
    PyObject *unflushed_new = PyLong_FromLongLong(unflushed + 1);
    if (unflushed_new == NULL || PyDict_SetItem(log, s_unflushed, unflushed_new) < 0) {
        Py_XDECREF(unflushed_new);
        return -1;
    }
    Py_DECREF(unflushed_new);

    Py_ssize_t offset = PyByteArray_GET_SIZE(chunk);
    PyObject *entries = PyDict_GetItemWithError(index, channel);
    if (entries == NULL) {
        if (PyErr_Occurred())
            return -1;
        entries = PyList_New(0);
        if (entries == NULL)
            return -1;
        int rc = PyDict_SetItem(index, channel, entries);
        Py_DECREF(entries); /* held by the index */
        if (rc < 0)
            return -1;
    } else if (!PyList_CheckExact(entries)) {
        PyErr_SetString(PyExc_TypeError, "imu_read: a message index is not a list");
        return -1;
    }
    PyObject *t_obj = PyLong_FromLongLong(t_ns), *at = PyLong_FromSsize_t(offset);
    int rc = (t_obj == NULL || at == NULL) ? -1
             : (PyList_Append(entries, t_obj) < 0 || PyList_Append(entries, at) < 0) ? -1 : 0;
    Py_XDECREF(t_obj);
    Py_XDECREF(at);
    if (rc < 0)
        return -1;

    Py_ssize_t data_size = head_size + body_size;
    if (PyByteArray_Resize(chunk, offset + MESSAGE_HEAD + data_size) < 0)
        return -1;
    unsigned char *b = (unsigned char *)PyByteArray_AS_STRING(chunk) + offset;
    b[0] = OP_MESSAGE;
    le(b + 1, (uint64_t)(MESSAGE_FIXED + data_size), 8);
    le(b + 9, channel_id, 2);
    le(b + 11, seq, 4);
    le(b + 15, (uint64_t)t_ns, 8);
    le(b + 23, (uint64_t)t_ns, 8);
    memcpy(b + MESSAGE_HEAD, head, (size_t)head_size);
    if (body_size)
        memcpy(b + MESSAGE_HEAD + head_size, body, (size_t)body_size);
    return offset + MESSAGE_HEAD + data_size;
}

/* The channel's id when it is an int an MCAP record holds (u16), else -1. */
static long channel_of(PyObject *v)
{
    if (!PyLong_CheckExact(v))
        return -1;
    long c = PyLong_AsLong(v);
    if (c == -1 && PyErr_Occurred()) {
        PyErr_Clear();
        return -1;
    }
    return (c < 0 || c > 0xFFFF) ? -1 : c;
}

static PyObject *imu_read(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 6 || !PyTuple_Check(args[0]) || PyTuple_GET_SIZE(args[0]) != 4 ||
        !PyDict_Check(PyTuple_GET_ITEM(args[0], 0)) ||
        !PyDict_Check(PyTuple_GET_ITEM(args[0], 1))) {
        PyErr_SetString(PyExc_TypeError, "imu_read((vars(LogWriter), vars(ChunkedWriter), "
                        "ImuSample, dumps), raw_channel, imu_channel, t_ns, data, sample)");
        return NULL;
    }
    PyObject *log = PyTuple_GET_ITEM(args[0], 0), *writer = PyTuple_GET_ITEM(args[0], 1);
    PyObject *sample_type = PyTuple_GET_ITEM(args[0], 2), *dumps = PyTuple_GET_ITEM(args[0], 3);
    PyObject *sample = args[5];
    long raw_channel = channel_of(args[1]), imu_channel = channel_of(args[2]);
    long long t_raw = time_of(args[3]);
    if ((PyObject *)Py_TYPE(sample) != sample_type || raw_channel < 0 || imu_channel < 0 ||
        t_raw < 0 || !PyBytes_CheckExact(args[4]))
        return PyLong_FromLong(0);

    /* the sample: the common one, every number finite, or declined */
    PyObject *fields[8] = {NULL};
    PyObject *names[8] = {s_t_ns, s_acc, s_gyro, s_temp, s_angle, s_mag, s_quat, s_device};
    PyObject *result = NULL;
    for (int i = 0; i < 8; i++) {
        fields[i] = PyObject_GetAttr(sample, names[i]);
        if (fields[i] == NULL)
            goto done;
    }
    double acc[3], gyro[3], temp = 0.0;
    long long t_ns = time_of(fields[0]);
    int has_temp = fields[3] != Py_None;
    if (t_ns < 0 || !three_floats(fields[1], acc) || !three_floats(fields[2], gyro) ||
        (has_temp && (!PyFloat_CheckExact(fields[3]) ||
                      !isfinite(temp = PyFloat_AS_DOUBLE(fields[3])))) ||
        fields[4] != Py_None || fields[5] != Py_None || fields[6] != Py_None ||
        fields[7] != Py_None) {
        result = PyLong_FromLong(0);
        goto done;
    }

    /* its JSON, whole before anything is written */
    char json[JSON_MAX], *p = json, *end = json + JSON_MAX - 1;
    p = put(p, "{\"type\":\"ImuSample\",\"timestamp\":{\"sec\":");
    p = put_u64(p, (uint64_t)(t_ns / 1000000000));
    p = put(p, ",\"nsec\":");
    p = put_u64(p, (uint64_t)(t_ns % 1000000000));
    p = put(p, "},\"t_ns\":");
    p = put_u64(p, (uint64_t)t_ns);
    p = put(p, ",\"acc_mps2\":");
    p = put_json(p, end - 16, dumps, fields[1]);
    if (p != NULL) {
        p = put(p, ",\"gyro_rps\":");
        p = put_json(p, end - 20, dumps, fields[2]);
    }
    if (p != NULL && has_temp) {
        p = put(p, ",\"temperature_c\":");
        p = put_json(p, end, dumps, fields[3]);
    }
    if (p == NULL)
        goto done;
    *p++ = '}';

    /* the /raw record: uwbd.Raw {data} (field 1, bytes), nothing for no bytes */
    const char *data = PyBytes_AS_STRING(args[4]);
    Py_ssize_t n = PyBytes_GET_SIZE(args[4]);
    char head[11];
    Py_ssize_t head_size = 0;
    if (n > 0) {
        head[head_size++] = 0x0A;
        for (uint64_t v = (uint64_t)n; ; v >>= 7) {
            if (v <= 0x7F) {
                head[head_size++] = (char)v;
                break;
            }
            head[head_size++] = (char)((v & 0x7F) | 0x80);
        }
    }
    PyObject *size_obj = PyDict_GetItemWithError(writer, s_chunk_size);
    Py_ssize_t chunk_size = size_obj == NULL ? -1 : PyLong_AsSsize_t(size_obj);
    if (chunk_size == -1 && (PyErr_Occurred() || size_obj == NULL)) {
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_TypeError, "imu_read: the writer has no _chunk_size");
        goto done;
    }
    Py_ssize_t size = add_message(log, writer, args[1], (unsigned)raw_channel, t_raw, head,
                                  head_size, data, n);
    if (size < 0)
        goto done;
    if (size > chunk_size) {
        result = PyLong_FromLong(1);
        goto done;
    }
    size = add_message(log, writer, args[2], (unsigned)imu_channel, t_ns, json, p - json,
                       NULL, 0);
    if (size >= 0)
        result = PyLong_FromLong(size > chunk_size ? 3 : 2);
done:
    for (int i = 0; i < 8; i++)
        Py_XDECREF(fields[i]);
    return result;
}

static PyMethodDef records_methods[] = {
    {"imu_read", (PyCFunction)(void (*)(void))imu_read, METH_FASTCALL,
     "A read's /raw record and its IMU sample's record, as LogWriter.read writes them."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef records_module = {
    PyModuleDef_HEAD_INIT, "_records", "The output log's most common records.", -1,
    records_methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__records(void)
{
    struct {
        PyObject **slot;
        const char *name;
    } names[] = {
        {&s_t_ns, "t_ns"}, {&s_acc, "acc_mps2"}, {&s_gyro, "gyro_rps"},
        {&s_temp, "temperature_c"}, {&s_angle, "angle_deg"}, {&s_mag, "mag_raw"},
        {&s_quat, "quaternion_wire"}, {&s_device, "device_time_ns"},
        {&s_sequence, "_sequence"}, {&s_unflushed, "unflushed"}, {&s_chunk, "_chunk"},
        {&s_index, "_index"}, {&s_chunk_size, "_chunk_size"},
    };
    for (size_t i = 0; i < sizeof names / sizeof names[0]; i++)
        if ((*names[i].slot = PyUnicode_InternFromString(names[i].name)) == NULL)
            return NULL;
    return PyModule_Create(&records_module);
}
