/* uwbd.logs._chunk.ChunkBuffer: the open chunk of uwbd's MCAP writer (uwbd/logs/chunked.py)
 * and its message indexes, per message in C.
 *
 * A log takes ~600 messages a second. Each is a Message record (opcode 0x05: record length
 * u64, channel id u16, sequence u32, log time u64, publish time u64 = log time, then the
 * data) appended to the chunk, and its (log time, offset) pair kept for the chunk's Message
 * Index records (opcode 0x07), one per channel in the order the chunk first saw it. The
 * reference is chunked.PyChunk (the same methods in Python); the files are the same, byte
 * for byte (tests/test_log_records.py).
 *
 *   ChunkBuffer()
 *   .add(channel_id, log_time, data, sequence) -> the chunk's length now; ValueError (the
 *        chunk unchanged) for a value its field cannot hold
 *   .append(record)    a whole record (schema, channel) into the chunk
 *   .size              the chunk's length
 *   .take() -> None when no message is in it, else (data, indexes, start, end, messages):
 *        indexes = ((channel_id, messages, Message Index record), ...); the chunk starts anew
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

#include "_chunk_layout.h" /* the records' heads, generated from uwbd/logs/records.py */

/* the record's content before its data: all of the head after its opcode and length */
#define MESSAGE_FIXED (MESSAGE_HEAD - MESSAGE_CHANNEL_ID_AT)

typedef struct {
    unsigned channel;
    uint64_t *pairs; /* log time, offset, … */
    Py_ssize_t count, cap;
} Index;

typedef struct {
    PyObject_HEAD
    unsigned char *data;
    Py_ssize_t len, cap;
    Index *indexes; /* in the order the chunk first saw each channel */
    Py_ssize_t n_indexes, cap_indexes;
} ChunkBuffer;

static int reserve(void **buf, Py_ssize_t *cap, Py_ssize_t need, size_t item)
{
    if (need <= *cap)
        return 0;
    Py_ssize_t grown = *cap ? *cap : 16;
    while (grown < need)
        grown *= 2;
    void *p = PyMem_Realloc(*buf, (size_t)grown * item);
    if (p == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    *buf = p;
    *cap = grown;
    return 0;
}

static void put_le(unsigned char *p, uint64_t v, int bytes)
{
    for (int i = 0; i < bytes; i++)
        p[i] = (unsigned char)(v >> (8 * i));
}

static Index *index_of(ChunkBuffer *s, unsigned channel)
{
    for (Py_ssize_t i = 0; i < s->n_indexes; i++)
        if (s->indexes[i].channel == channel)
            return &s->indexes[i];
    if (reserve((void **)&s->indexes, &s->cap_indexes, s->n_indexes + 1, sizeof(Index)) < 0)
        return NULL;
    Index *ix = &s->indexes[s->n_indexes++];
    memset(ix, 0, sizeof *ix);
    ix->channel = channel;
    return ix;
}

static int get_u64(PyObject *obj, uint64_t max, uint64_t *out, const char *what)
{
    int overflow = 0;
    long long v = PyLong_AsLongLongAndOverflow(obj, &overflow);
    if (v == -1 && PyErr_Occurred())
        return -1;
    if (overflow > 0) { /* above 2**63: the u64 fields may hold it */
        unsigned long long u = PyLong_AsUnsignedLongLong(obj);
        if (u == (unsigned long long)-1 && PyErr_Occurred()) {
            PyErr_Clear();
            PyErr_Format(PyExc_ValueError, "%s out of range for its MCAP field", what);
            return -1;
        }
        if (u > max) {
            PyErr_Format(PyExc_ValueError, "%s out of range for its MCAP field", what);
            return -1;
        }
        *out = u;
        return 0;
    }
    if (overflow < 0 || v < 0 || (uint64_t)v > max) {
        PyErr_Format(PyExc_ValueError, "%s out of range for its MCAP field", what);
        return -1;
    }
    *out = (uint64_t)v;
    return 0;
}

static PyObject *chunk_add(ChunkBuffer *s, PyObject *const *args, Py_ssize_t nargs)
{
    uint64_t channel, t, sequence;
    if (nargs != 4) {
        PyErr_SetString(PyExc_TypeError, "add(channel_id, log_time, data, sequence)");
        return NULL;
    }
    if (get_u64(args[0], 0xFFFF, &channel, "channel id") < 0 ||
        get_u64(args[1], UINT64_MAX, &t, "log time") < 0 ||
        get_u64(args[3], 0xFFFFFFFF, &sequence, "sequence") < 0)
        return NULL;
    Py_buffer view;
    if (PyObject_GetBuffer(args[2], &view, PyBUF_SIMPLE) < 0)
        return NULL;
    Index *ix = index_of(s, (unsigned)channel);
    if (ix == NULL ||
        reserve((void **)&ix->pairs, &ix->cap, ix->count * 2 + 2, sizeof(uint64_t)) < 0 ||
        reserve((void **)&s->data, &s->cap, s->len + MESSAGE_HEAD + view.len, 1) < 0) {
        PyBuffer_Release(&view);
        return NULL;
    }
    ix->pairs[2 * ix->count] = t;
    ix->pairs[2 * ix->count + 1] = (uint64_t)s->len;
    ix->count++;
    unsigned char *p = s->data + s->len;
    put_le(p + MESSAGE_OPCODE_AT, OP_MESSAGE, MESSAGE_OPCODE_SIZE);
    put_le(p + MESSAGE_RECORD_LENGTH_AT, (uint64_t)(MESSAGE_FIXED + view.len),
           MESSAGE_RECORD_LENGTH_SIZE);
    put_le(p + MESSAGE_CHANNEL_ID_AT, channel, MESSAGE_CHANNEL_ID_SIZE);
    put_le(p + MESSAGE_SEQUENCE_AT, sequence, MESSAGE_SEQUENCE_SIZE);
    put_le(p + MESSAGE_LOG_TIME_AT, t, MESSAGE_LOG_TIME_SIZE);
    put_le(p + MESSAGE_PUBLISH_TIME_AT, t, MESSAGE_PUBLISH_TIME_SIZE);
    memcpy(p + MESSAGE_HEAD, view.buf, (size_t)view.len);
    s->len += MESSAGE_HEAD + view.len;
    PyBuffer_Release(&view);
    return PyLong_FromSsize_t(s->len);
}

static PyObject *chunk_append(ChunkBuffer *s, PyObject *record)
{
    Py_buffer view;
    if (PyObject_GetBuffer(record, &view, PyBUF_SIMPLE) < 0)
        return NULL;
    int rc = reserve((void **)&s->data, &s->cap, s->len + view.len, 1);
    if (rc == 0) {
        memcpy(s->data + s->len, view.buf, (size_t)view.len);
        s->len += view.len;
    }
    PyBuffer_Release(&view);
    if (rc < 0)
        return NULL;
    Py_RETURN_NONE;
}

/* chunked._message_index: channel id u16, then the pairs as an array with a u32 length */
static PyObject *index_record(const Index *ix)
{
    Py_ssize_t size = 16 * ix->count;
    PyObject *out = PyBytes_FromStringAndSize(NULL, INDEX_HEAD + size);
    if (out == NULL)
        return NULL;
    unsigned char *p = (unsigned char *)PyBytes_AS_STRING(out);
    put_le(p + INDEX_OPCODE_AT, OP_MESSAGE_INDEX, INDEX_OPCODE_SIZE);
    put_le(p + INDEX_RECORD_LENGTH_AT, (uint64_t)(INDEX_HEAD - INDEX_CHANNEL_ID_AT + size),
           INDEX_RECORD_LENGTH_SIZE);
    put_le(p + INDEX_CHANNEL_ID_AT, ix->channel, INDEX_CHANNEL_ID_SIZE);
    put_le(p + INDEX_ARRAY_BYTES_AT, (uint64_t)size, INDEX_ARRAY_BYTES_SIZE);
    for (Py_ssize_t k = 0; k < 2 * ix->count; k++)
        put_le(p + INDEX_HEAD + 8 * k, ix->pairs[k], 8);
    return out;
}

static PyObject *chunk_take(ChunkBuffer *s, PyObject *unused)
{
    (void)unused;
    if (s->n_indexes == 0)
        Py_RETURN_NONE;
    uint64_t start = UINT64_MAX, end = 0;
    Py_ssize_t messages = 0;
    PyObject *indexes = PyTuple_New(s->n_indexes);
    for (Py_ssize_t i = 0; indexes != NULL && i < s->n_indexes; i++) {
        const Index *ix = &s->indexes[i];
        for (Py_ssize_t k = 0; k < ix->count; k++) {
            uint64_t t = ix->pairs[2 * k];
            start = t < start ? t : start;
            end = t > end ? t : end;
        }
        messages += ix->count;
        PyObject *record = index_record(ix);
        PyObject *item = record ? Py_BuildValue("(InN)", ix->channel, ix->count, record) : NULL;
        if (item == NULL)
            Py_CLEAR(indexes);
        else
            PyTuple_SET_ITEM(indexes, i, item);
    }
    PyObject *data = indexes ? PyBytes_FromStringAndSize((const char *)s->data, s->len) : NULL;
    PyObject *out = data ? Py_BuildValue("(NNKKn)", data, indexes, (unsigned long long)start,
                                         (unsigned long long)end, messages)
                         : NULL;
    if (out == NULL) {
        Py_XDECREF(indexes);
        return NULL;
    }
    for (Py_ssize_t i = 0; i < s->n_indexes; i++)
        PyMem_Free(s->indexes[i].pairs);
    s->n_indexes = 0;
    s->len = 0;
    return out;
}

static PyObject *get_size(ChunkBuffer *s, void *c)
{
    (void)c;
    return PyLong_FromSsize_t(s->len);
}

static void chunk_dealloc(ChunkBuffer *s)
{
    for (Py_ssize_t i = 0; i < s->n_indexes; i++)
        PyMem_Free(s->indexes[i].pairs);
    PyMem_Free(s->indexes);
    PyMem_Free(s->data);
    Py_TYPE(s)->tp_free((PyObject *)s);
}

static PyMethodDef chunk_methods[] = {
    {"add", (PyCFunction)(void (*)(void))chunk_add, METH_FASTCALL,
     "add(channel_id, log_time, data, sequence) -> the chunk's length: one Message record."},
    {"append", (PyCFunction)chunk_append, METH_O, "append(record): a whole record."},
    {"take", (PyCFunction)chunk_take, METH_NOARGS,
     "take() -> None, or (data, ((channel, messages, Message Index record), ...), start, "
     "end, messages); the chunk starts anew."},
    {NULL, NULL, 0, NULL},
};

static PyGetSetDef chunk_getset[] = {
    {"size", (getter)get_size, NULL, "The chunk's length in bytes.", NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

static PyTypeObject ChunkBufferType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "uwbd.logs._chunk.ChunkBuffer",
    .tp_doc = "The open MCAP chunk and its message indexes (chunked.PyChunk in C).",
    .tp_basicsize = sizeof(ChunkBuffer),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = PyType_GenericNew,
    .tp_dealloc = (destructor)chunk_dealloc,
    .tp_methods = chunk_methods,
    .tp_getset = chunk_getset,
};

static struct PyModuleDef chunk_module = {
    PyModuleDef_HEAD_INIT, "_chunk", "The open chunk of uwbd's MCAP writer, in C.", -1,
    NULL, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__chunk(void)
{
    if (PyType_Ready(&ChunkBufferType) < 0)
        return NULL;
    PyObject *m = PyModule_Create(&chunk_module);
    if (m != NULL && PyModule_AddObjectRef(m, "ChunkBuffer", (PyObject *)&ChunkBufferType) < 0)
        Py_CLEAR(m);
    return m;
}
