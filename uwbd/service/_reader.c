/* uwbd.service._reader: the daemon's serial reads, on a thread of their own.
 *
 * An IMU at 200 Hz makes ~200 reads a second; each woke the asyncio loop (a Python callback,
 * on caches gone cold since the last one) only to be held until the next pose was due
 * (uwbd.service.ports.ReadQueue). Here a C thread waits on the ports (epoll), reads each as
 * it becomes readable, stamps the read as uwbd's EpochClock does (Unix-epoch ns advancing
 * with CLOCK_MONOTONIC, taken when the read returns) and holds it. It wakes the loop (an
 * eventfd the loop watches) only when a read may change what subscribers see: one from an
 * "urgent" port (UWB), one at or after the time the next pose is due (set_due), a port lost,
 * or reads held for max_hold_ns. Python then takes the held reads (drain) in the order they
 * were read, and everything after that is as before: sources, times and order are those the
 * loop would have seen, so a log replays bit for bit either way.
 *
 * The thread touches no Python object and never takes the GIL: held reads live in a C
 * buffer under a mutex. A port is read under that mutex, and remove() takes it, so a port
 * is never read after remove() returns (its fd may then be closed and its number reused).
 *
 * Reader(offset_ns, max_hold_ns): offset_ns = time_ns() - monotonic_ns(), read once.
 *   .wake_fd               readable when there are reads to take
 *   .add(fd, source, urgent) / .remove(fd)
 *   .set_due(t_ns)         reads at or after t_ns wake the loop
 *   .drain() -> [(source, t_ns, data, error)]  data None: the port was lost; error is its
 *                          errno (0: end of file)
 *   .dropped_bytes         bytes not held because Python took nothing for 64 MB of reads
 *   .close()               stops the thread (also on garbage collection)
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <errno.h>
#include <pthread.h>
#include <signal.h>
#include <stdint.h>
#include <string.h>
#include <sys/epoll.h>
#include <sys/prctl.h>
#include <sys/eventfd.h>
#include <time.h>
#include <unistd.h>

#define MAX_SLOTS 64
#define READ_BYTES 4096 /* as uwbd.service.ports.READ_BYTES */
#define MAX_HELD_BYTES ((size_t)64 << 20)
#define STOP_KEY UINT64_MAX
#define EVENTS 16

typedef struct {
    int fd, source, urgent, active;
    uint32_t generation; /* of the slot, so a stale epoll event is known */
} Slot;

typedef struct {
    int source;
    int64_t t_ns;
    size_t offset, length;
} Held;

typedef struct {
    int source, error;
    int64_t t_ns;
} Loss;

typedef struct {
    PyObject_HEAD
    pthread_t thread;
    int running;
    pthread_mutex_t lock;
    int ep, wake_fd, stop_fd;
    int64_t offset_ns, max_hold_ns, due_ns;
    Slot slots[MAX_SLOTS];
    Held *held;
    size_t n_held, cap_held;
    char *bytes;
    size_t n_bytes, cap_bytes;
    Loss losses[MAX_SLOTS]; /* lost ports not yet taken: no allocation needed to say so */
    int n_losses;
    int signalled;
    unsigned long long dropped_bytes;
} Reader;

static int64_t now_ns(const Reader *r)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return r->offset_ns + (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

/* One held read; 0, or -1 when out of memory (the read is then dropped). */
static int hold(Reader *r, int source, int64_t t_ns, const char *data, size_t length)
{
    if (r->n_held == r->cap_held) {
        size_t cap = r->cap_held ? 2 * r->cap_held : 64;
        Held *h = realloc(r->held, cap * sizeof *h);
        if (h == NULL)
            return -1;
        r->held = h;
        r->cap_held = cap;
    }
    if (r->n_bytes + length > r->cap_bytes) {
        size_t cap = r->cap_bytes ? r->cap_bytes : 16384;
        while (cap < r->n_bytes + length)
            cap *= 2;
        char *b = realloc(r->bytes, cap);
        if (b == NULL)
            return -1;
        r->bytes = b;
        r->cap_bytes = cap;
    }
    if (length)
        memcpy(r->bytes + r->n_bytes, data, length);
    r->held[r->n_held++] = (Held){source, t_ns, r->n_bytes, length};
    r->n_bytes += length;
    return 0;
}

static void *run(void *arg)
{
    Reader *r = arg;
    struct epoll_event events[EVENTS];
    char buf[READ_BYTES];
    int timeout_ms = 100;
    prctl(PR_SET_NAME, "uwbd-reader", 0, 0, 0); /* the name top -H and ps -L show */
    for (;;) {
        int n = epoll_wait(r->ep, events, EVENTS, timeout_ms);
        if (n < 0 && errno != EINTR)
            n = 0; /* cannot happen with a valid epoll fd; keep waiting for stop */
        pthread_mutex_lock(&r->lock);
        int wake = 0, stop = 0;
        for (int i = 0; i < n; i++) {
            uint64_t key = events[i].data.u64;
            if (key == STOP_KEY) {
                stop = 1;
                continue;
            }
            Slot *s = &r->slots[key & 0xFFFFFFFFu];
            if (!s->active || s->generation != (uint32_t)(key >> 32))
                continue; /* removed since epoll_wait returned */
            ssize_t got = read(s->fd, buf, sizeof buf);
            int error = got < 0 ? errno : 0;
            /* a terminal whose VMIN is set (a batched port: ports.SerialSource.batch_reads)
             * gives at most 64 bytes a read (the kernel's chunk): what else is there now is
             * read too, as one read; an error or the end after it is the next round's */
            while (got > 0 && (size_t)got < sizeof buf) {
                ssize_t more = read(s->fd, buf + got, sizeof buf - (size_t)got);
                if (more <= 0)
                    break;
                got += more;
            }
            int64_t t_ns = now_ns(r);
            if (got > 0) {
                if (r->n_bytes + (size_t)got > MAX_HELD_BYTES ||
                    hold(r, s->source, t_ns, buf, (size_t)got) < 0)
                    r->dropped_bytes += (unsigned long long)got;
                else if (s->urgent || t_ns >= r->due_ns)
                    wake = 1;
            } else if (got == 0 || (error != EAGAIN && error != EINTR) ||
                       (events[i].events & (EPOLLERR | EPOLLHUP))) {
                /* end of file, an error, or nothing to read from a port that hangs up or
                 * errs (epoll would report it again at once): lost */
                epoll_ctl(r->ep, EPOLL_CTL_DEL, s->fd, NULL);
                s->active = 0;
                s->generation++;
                if (r->n_losses < MAX_SLOTS) /* one per port added: never full */
                    r->losses[r->n_losses++] = (Loss){s->source, got == 0 ? 0 : (
                        error == EAGAIN ? EIO : error), t_ns};
                wake = 1;
            }
        }
        timeout_ms = 100;
        if (r->n_held && !r->signalled) { /* wake when the oldest has been held long enough */
            int64_t left = r->held[0].t_ns + r->max_hold_ns - now_ns(r);
            if (left <= 0)
                wake = 1;
            else if (left < 100000000)
                timeout_ms = (int)((left + 999999) / 1000000);
        }
        if (wake && !r->signalled) {
            uint64_t one = 1;
            if (write(r->wake_fd, &one, sizeof one) == sizeof one)
                r->signalled = 1;
        }
        pthread_mutex_unlock(&r->lock);
        if (stop)
            return NULL;
    }
}

static void stop_thread(Reader *r)
{
    if (r->running) {
        uint64_t one = 1;
        if (write(r->stop_fd, &one, sizeof one) != sizeof one) {
            /* an eventfd write fails only at its counter's maximum: the thread is woken */
        }
        pthread_join(r->thread, NULL); /* within a loop turn: the thread needs no GIL */
        r->running = 0;
    }
    int *fds[3] = {&r->ep, &r->wake_fd, &r->stop_fd};
    for (int i = 0; i < 3; i++)
        if (*fds[i] >= 0) {
            close(*fds[i]);
            *fds[i] = -1;
        }
}

static int reader_init(Reader *r, PyObject *args, PyObject *kwds)
{
    static char *kwlist[] = {"offset_ns", "max_hold_ns", NULL};
    long long offset, max_hold;
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "LL", kwlist, &offset, &max_hold))
        return -1;
    if (r->running || r->ep >= 0) {
        PyErr_SetString(PyExc_RuntimeError, "Reader: already started");
        return -1;
    }
    r->offset_ns = offset;
    r->max_hold_ns = max_hold;
    r->due_ns = INT64_MIN;
    r->ep = epoll_create1(EPOLL_CLOEXEC);
    r->wake_fd = eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
    r->stop_fd = eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
    struct epoll_event ev = {.events = EPOLLIN, .data.u64 = STOP_KEY};
    if (r->ep < 0 || r->wake_fd < 0 || r->stop_fd < 0 ||
        epoll_ctl(r->ep, EPOLL_CTL_ADD, r->stop_fd, &ev) < 0) {
        PyErr_SetFromErrno(PyExc_OSError);
        stop_thread(r);
        return -1;
    }
    sigset_t all, old; /* signals go to the main thread, as Python expects */
    sigfillset(&all);
    pthread_sigmask(SIG_SETMASK, &all, &old);
    int rc = pthread_create(&r->thread, NULL, run, r);
    pthread_sigmask(SIG_SETMASK, &old, NULL);
    if (rc != 0) {
        errno = rc;
        PyErr_SetFromErrno(PyExc_OSError);
        stop_thread(r);
        return -1;
    }
    r->running = 1;
    return 0;
}

static PyObject *reader_new(PyTypeObject *type, PyObject *args, PyObject *kwds)
{
    (void)args;
    (void)kwds;
    Reader *r = (Reader *)type->tp_alloc(type, 0);
    if (r == NULL)
        return NULL;
    r->ep = r->wake_fd = r->stop_fd = -1;
    pthread_mutex_init(&r->lock, NULL);
    return (PyObject *)r;
}

static void reader_dealloc(Reader *r)
{
    stop_thread(r);
    pthread_mutex_destroy(&r->lock);
    free(r->held);
    free(r->bytes);
    Py_TYPE(r)->tp_free((PyObject *)r);
}

static int check_open(Reader *r)
{
    if (!r->running) {
        PyErr_SetString(PyExc_ValueError, "Reader: closed");
        return -1;
    }
    return 0;
}

static PyObject *reader_add(Reader *r, PyObject *args)
{
    int fd, source, urgent;
    if (!PyArg_ParseTuple(args, "iip", &fd, &source, &urgent) || check_open(r) < 0)
        return NULL;
    pthread_mutex_lock(&r->lock);
    int k = 0;
    while (k < MAX_SLOTS && r->slots[k].active)
        k++;
    int rc = -1, error = EMFILE;
    if (k < MAX_SLOTS) {
        Slot *s = &r->slots[k];
        struct epoll_event ev = {.events = EPOLLIN,
                                 .data.u64 = ((uint64_t)s->generation << 32) | (uint32_t)k};
        rc = epoll_ctl(r->ep, EPOLL_CTL_ADD, fd, &ev);
        error = errno;
        if (rc == 0) {
            s->fd = fd;
            s->source = source;
            s->urgent = urgent;
            s->active = 1;
        }
    }
    pthread_mutex_unlock(&r->lock);
    if (rc < 0) {
        errno = error;
        return PyErr_SetFromErrno(PyExc_OSError);
    }
    Py_RETURN_NONE;
}

/* After this returns the port is not read again; a port the thread dropped (lost) or never
 * had is no error. */
static PyObject *reader_remove(Reader *r, PyObject *arg)
{
    int fd = PyLong_AsLong(arg);
    if (fd == -1 && PyErr_Occurred())
        return NULL;
    pthread_mutex_lock(&r->lock);
    for (int k = 0; k < MAX_SLOTS; k++) {
        Slot *s = &r->slots[k];
        if (s->active && s->fd == fd) {
            epoll_ctl(r->ep, EPOLL_CTL_DEL, fd, NULL);
            s->active = 0;
            s->generation++;
        }
    }
    pthread_mutex_unlock(&r->lock);
    Py_RETURN_NONE;
}

static PyObject *reader_set_due(Reader *r, PyObject *arg)
{
    int overflow = 0;
    long long due = PyLong_AsLongLongAndOverflow(arg, &overflow);
    if (due == -1 && PyErr_Occurred())
        return NULL;
    if (overflow)
        due = overflow < 0 ? INT64_MIN : INT64_MAX;
    pthread_mutex_lock(&r->lock);
    r->due_ns = due;
    pthread_mutex_unlock(&r->lock);
    Py_RETURN_NONE;
}

static PyObject *reader_drain(Reader *r, PyObject *Py_UNUSED(ignored))
{
    if (check_open(r) < 0)
        return NULL;
    uint64_t count;
    if (read(r->wake_fd, &count, sizeof count) < 0 && errno != EAGAIN)
        return PyErr_SetFromErrno(PyExc_OSError);
    pthread_mutex_lock(&r->lock); /* the held reads taken; the thread goes on into new ones */
    Held *held = r->held;
    char *bytes = r->bytes;
    size_t n = r->n_held;
    Loss losses[MAX_SLOTS];
    int n_losses = r->n_losses;
    memcpy(losses, r->losses, sizeof losses);
    r->held = NULL;
    r->bytes = NULL;
    r->n_held = r->cap_held = r->n_bytes = r->cap_bytes = 0;
    r->n_losses = 0;
    r->signalled = 0;
    pthread_mutex_unlock(&r->lock);
    /* (out of memory here, what was taken is lost with the process's other troubles) */
    PyObject *out = PyList_New((Py_ssize_t)n + n_losses);
    for (int k = 0; out != NULL && k < n_losses; k++) { /* after the reads before them */
        PyObject *item = Py_BuildValue("(iLOi)", losses[k].source, (long long)losses[k].t_ns,
                                       Py_None, losses[k].error);
        if (item == NULL)
            Py_CLEAR(out);
        else
            PyList_SET_ITEM(out, (Py_ssize_t)n + k, item);
    }
    for (size_t i = 0; out != NULL && i < n; i++) {
        Held *h = &held[i];
        PyObject *data = PyBytes_FromStringAndSize(bytes + h->offset, (Py_ssize_t)h->length);
        PyObject *item = data == NULL ? NULL
            : Py_BuildValue("(iLNi)", h->source, (long long)h->t_ns, data, 0);
        if (item == NULL)
            Py_CLEAR(out);
        else
            PyList_SET_ITEM(out, (Py_ssize_t)i, item);
    }
    free(held);
    free(bytes);
    return out;
}

static PyObject *reader_close(Reader *r, PyObject *Py_UNUSED(ignored))
{
    stop_thread(r);
    Py_RETURN_NONE;
}

static PyObject *reader_wake_fd(Reader *r, void *closure)
{
    (void)closure;
    return PyLong_FromLong(r->wake_fd);
}

static PyObject *reader_dropped(Reader *r, void *closure)
{
    (void)closure;
    pthread_mutex_lock(&r->lock);
    unsigned long long dropped = r->dropped_bytes;
    pthread_mutex_unlock(&r->lock);
    return PyLong_FromUnsignedLongLong(dropped);
}

static PyMethodDef reader_methods[] = {
    {"add", (PyCFunction)reader_add, METH_VARARGS,
     "add(fd, source, urgent): read this port; its reads carry source."},
    {"remove", (PyCFunction)reader_remove, METH_O,
     "remove(fd): read the port no more (done when this returns)."},
    {"set_due", (PyCFunction)reader_set_due, METH_O,
     "set_due(t_ns): reads at or after t_ns wake the loop."},
    {"drain", (PyCFunction)reader_drain, METH_NOARGS,
     "The held reads, in order: [(source, t_ns, data, error)]; data None: port lost."},
    {"close", (PyCFunction)reader_close, METH_NOARGS, "Stop the thread; again: nothing."},
    {NULL, NULL, 0, NULL},
};

static PyGetSetDef reader_getset[] = {
    {"wake_fd", (getter)reader_wake_fd, NULL, "readable when there are reads to take", NULL},
    {"dropped_bytes", (getter)reader_dropped, NULL, "bytes read but not held (overflow)",
     NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

static PyTypeObject ReaderType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "uwbd.service._reader.Reader",
    .tp_basicsize = sizeof(Reader),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Serial reads on a thread of their own (see the module).",
    .tp_new = reader_new,
    .tp_init = (initproc)reader_init,
    .tp_dealloc = (destructor)reader_dealloc,
    .tp_methods = reader_methods,
    .tp_getset = reader_getset,
};

static struct PyModuleDef reader_module = {
    PyModuleDef_HEAD_INIT, "_reader",
    "The daemon's serial reads on a thread of their own (uwbd/service/ports.py).", -1,
    NULL, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__reader(void)
{
    if (PyType_Ready(&ReaderType) < 0)
        return NULL;
    PyObject *m = PyModule_Create(&reader_module);
    if (m == NULL)
        return NULL;
    Py_INCREF(&ReaderType);
    if (PyModule_AddObject(m, "Reader", (PyObject *)&ReaderType) < 0) {
        Py_DECREF(&ReaderType);
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
