/* The State type: the error-state EKF's numbers in memory of its own (docs/ekf.md), and the
 * operations on them, each a step of that page:
 *
 *   predict        §2   one IMU sample (body axes) into the nominal state and the interval sums
 *   propagate      §3   P ← Φ P Φᵀ + Q_d over the interval, the Gauss–Markov decays
 *   coast          §3   constant velocity without the IMU
 *   update         §5   rows fused one scalar at a time, then injected and reset
 *   fuse_ranges    §4+5 an epoch's range rows (mm_range.c) and extra rows, fused
 *   fuse_period    §2-5 a pose period's IMU samples and single ranges, in one call
 *   range_check    §6   an epoch's innovations and single-fault estimates, for the checks
 *   rotate_heading §6   the coarse heading alignment's turn
 *   clamp, widen, add_variances, set_covariance, move_to: §6's covariance and state repairs
 *   adopt          §6   the main filter becomes one of the bank's sub-filters
 *   separation_numbers  §6   the bank's numbers for the separation test
 *   pose_numbers        the pose's numbers
 *
 * The state is one block of doubles, exported read-only through the buffer protocol:
 * p (3), v (3), q (4: w x y z), b_g (3), b_a (3), b_r (m), P (n×n, row-major), last_dx (n),
 * with n = 15 + m; then the bank (§6, integrity): K sub-filters, each leaving one anchor's
 * ranges out (or, with variances of its own added at each start, estimating states the
 * main filter holds known: the lever arm's), as their offsets from the nominal state d_k
 * (K×n) and covariances P_k (K×n×n). Every operation above advances the bank with the main
 * filter: the same Φ and Q, the same rows with the main filter's weights (its decisions),
 * but anchor k's rows left out of sub-filter k; the heading's turn turns them too; a
 * restore, a move or an adoption starts the bank anew from the main filter (d_k = 0,
 * P_k = P + its variances). Python reads the block as numpy views (eskf.CoreEskf) and
 * changes it only through the operations. The reference is eskf.Eskf, in pure Python. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>

#include "_core.h"

typedef struct {
    PyObject_HEAD
    Py_ssize_t n, m, len;
    double *x; /* the exported block */
    double *p, *v, *q, *bg, *ba, *br, *P, *last_dx;
    double gravity, T, sum_fn[3], sum_w[3], dv_epoch[3];
    double Phi_epoch[N_CORE * N_CORE], *decay_epoch; /* since take_epoch, for smoothing */
    int keep_transition, epoch_propagated;
    double *q_rate;          /* n: the diagonal of Q per second */
    Py_ssize_t n_markov;     /* the Gauss–Markov states: */
    Py_ssize_t *markov_cols; /* their columns, ascending */
    double *markov_tau, *markov_var; /* τ and stationary variance each */
    double *work;            /* n×n + 15 n + 4 n doubles */
    double *rows;            /* range rows: H (k×n), y, R; grown as needed */
    Py_ssize_t rows_cap;
    Py_ssize_t bank;         /* K sub-filters: */
    long long *bank_anchor;  /* the anchor each leaves out */
    double *bank_var;        /* K×n: the variances each adds to P's diagonal at a start */
    double *bank_d, *bank_P; /* in the exported block: d_k (K×n), P_k (K×n×n) */
} State;

static void set_identity(double *A, Py_ssize_t n)
{
    memset(A, 0, sizeof(double) * n * n);
    for (Py_ssize_t i = 0; i < n; i++)
        A[i * n + i] = 1.0;
}

/* Sub-filter k started anew from the main filter: d_k = 0, P_k = P + diag(bank_var_k). */
static void member_reset(State *self, Py_ssize_t k)
{
    Py_ssize_t n = self->n;
    double *Pk = self->bank_P + k * n * n;
    memset(self->bank_d + k * n, 0, sizeof(double) * (size_t)n);
    memcpy(Pk, self->P, sizeof(double) * (size_t)(n * n));
    for (Py_ssize_t i = 0; i < n; i++)
        Pk[i * n + i] += self->bank_var[k * n + i];
}

/* The bank started anew: every sub-filter. */
static void bank_reset(State *self)
{
    for (Py_ssize_t k = 0; k < self->bank; k++)
        member_reset(self, k);
}

/* State(p, v, q, b_g, b_a, b_r, P0, q_rate, tau, markov_var, gravity, bank, bank_var): n
 * from P0 (n×n), m = n − 15 range-model states: b_r, tau (inf: a random walk, else
 * Gauss–Markov with τ) and markov_var (their stationary variances) m each, q_rate n; bank:
 * the anchor each sub-filter leaves out (a sequence of ints, maybe empty; one no row is
 * of leaves none out); bank_var: K×n variances each sub-filter adds to the main filter's
 * diagonal whenever the bank starts anew (states only it estimates). */
static int state_init(State *self, PyObject *args, PyObject *kwds)
{
    PyObject *po, *vo, *qo, *bgo, *bao, *bro, *P0, *qro, *tauo, *varo, *banko, *bvaro;
    double gravity;
    if (kwds != NULL && PyDict_GET_SIZE(kwds)) {
        PyErr_SetString(PyExc_TypeError, "State takes no keyword arguments");
        return -1;
    }
    if (self->x != NULL) {
        PyErr_SetString(PyExc_TypeError, "a State is made once");
        return -1;
    }
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOdOO", &po, &vo, &qo, &bgo, &bao, &bro, &P0, &qro,
                          &tauo, &varo, &gravity, &banko, &bvaro))
        return -1;
    PyObject *bank_seq = PySequence_Fast(banko, "bank: a sequence of anchor ids");
    if (bank_seq == NULL)
        return -1;
    Py_ssize_t K = PySequence_Fast_GET_SIZE(bank_seq);
    PyMem_Free(self->bank_anchor); /* (an earlier call that failed before the block) */
    self->bank_anchor = PyMem_Calloc((size_t)(K + 1), sizeof(long long));
    if (self->bank_anchor == NULL) {
        Py_DECREF(bank_seq);
        PyErr_NoMemory();
        return -1;
    }
    for (Py_ssize_t k = 0; k < K; k++)
        self->bank_anchor[k] = PyLong_AsLongLong(PySequence_Fast_GET_ITEM(bank_seq, k));
    Py_DECREF(bank_seq);
    if (PyErr_Occurred())
        return -1;
    self->bank = K;
    Py_buffer Pb;
    if (uwbd_get_doubles(P0, &Pb, -1, 0, "P0") < 0)
        return -1;
    Py_ssize_t n = (Py_ssize_t)sqrt((double)(Pb.len / 8));
    if (n * n * 8 != Pb.len || n < N_CORE) {
        PyBuffer_Release(&Pb);
        PyErr_SetString(PyExc_ValueError, "P0 must be square, at least 15x15");
        return -1;
    }
    Py_buffer Vb;
    if (uwbd_get_doubles(bvaro, &Vb, K * n, 0, "bank_var") < 0) {
        PyBuffer_Release(&Pb);
        return -1;
    }
    PyMem_Free(self->bank_var);
    self->bank_var = PyMem_Calloc((size_t)(K * n + 1), sizeof(double));
    if (self->bank_var == NULL) {
        PyBuffer_Release(&Pb);
        PyBuffer_Release(&Vb);
        PyErr_NoMemory();
        return -1;
    }
    memcpy(self->bank_var, Vb.buf, sizeof(double) * (size_t)(K * n));
    PyBuffer_Release(&Vb);
    Py_ssize_t m = n - N_CORE;
    self->n = n;
    self->m = m;
    self->len = NOM_AUX + m + n * n + n + K * (n + n * n);
    self->x = PyMem_Calloc((size_t)self->len, sizeof(double));
    self->decay_epoch = PyMem_Calloc((size_t)(m + 1), sizeof(double));
    self->q_rate = PyMem_Calloc((size_t)n, sizeof(double));
    self->markov_cols = PyMem_Calloc((size_t)(m + 1), sizeof(Py_ssize_t));
    self->markov_tau = PyMem_Calloc((size_t)(2 * m + 2), sizeof(double));
    self->work = PyMem_Calloc((size_t)(n * n + (N_CORE + 4) * n), sizeof(double));
    if (!self->x || !self->decay_epoch || !self->q_rate || !self->markov_cols ||
        !self->markov_tau || !self->work) {
        PyBuffer_Release(&Pb);
        PyErr_NoMemory();
        return -1;
    }
    self->markov_var = self->markov_tau + m + 1;
    double *x = self->x;
    self->p = x + NOM_P, self->v = x + NOM_V, self->q = x + NOM_Q, self->bg = x + NOM_BG;
    self->ba = x + NOM_BA, self->br = x + NOM_AUX, self->P = x + NOM_AUX + m;
    self->last_dx = self->P + n * n;
    self->bank_d = self->last_dx + n;
    self->bank_P = self->bank_d + K * n;
    memcpy(self->P, Pb.buf, sizeof(double) * n * n);
    PyBuffer_Release(&Pb);
    bank_reset(self);
    double *tau = PyMem_Calloc((size_t)(2 * m + 1), sizeof(double)), *var = tau + m;
    if (tau == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    int bad = uwbd_get_vec(po, self->p, 3, "p") || uwbd_get_vec(vo, self->v, 3, "v") ||
              uwbd_get_vec(qo, self->q, 4, "q") || uwbd_get_vec(bgo, self->bg, 3, "b_g") ||
              uwbd_get_vec(bao, self->ba, 3, "b_a") || uwbd_get_vec(bro, self->br, m, "b_r") ||
              uwbd_get_vec(qro, self->q_rate, n, "q_rate") ||
              uwbd_get_vec(tauo, tau, m, "tau") || uwbd_get_vec(varo, var, m, "markov_var");
    if (!bad)
        for (Py_ssize_t a = 0; a < m; a++)
            if (isfinite(tau[a])) {
                Py_ssize_t i = self->n_markov++;
                self->markov_cols[i] = N_CORE + a;
                self->markov_tau[i] = tau[a];
                self->markov_var[i] = var[a];
            }
    PyMem_Free(tau);
    if (bad)
        return -1;
    self->gravity = gravity;
    self->keep_transition = 1;
    set_identity(self->Phi_epoch, N_CORE);
    for (Py_ssize_t a = 0; a < m; a++)
        self->decay_epoch[a] = 1.0;
    return 0;
}

static void state_dealloc(State *self)
{
    PyMem_Free(self->x);
    PyMem_Free(self->decay_epoch);
    PyMem_Free(self->q_rate);
    PyMem_Free(self->markov_cols);
    PyMem_Free(self->markov_tau);
    PyMem_Free(self->work);
    PyMem_Free(self->rows);
    PyMem_Free(self->bank_anchor);
    PyMem_Free(self->bank_var);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int state_getbuffer(State *self, Py_buffer *view, int flags)
{
    if (self->x == NULL) {
        PyErr_SetString(PyExc_BufferError, "the State was not made");
        view->obj = NULL;
        return -1;
    }
    /* read only: the state changes through the operations alone */
    return PyBuffer_FillInfo(view, (PyObject *)self, self->x, self->len * 8, 1, flags);
}

static PyBufferProcs state_as_buffer = {(getbufferproc)state_getbuffer, NULL};

static int check_args(Py_ssize_t nargs, Py_ssize_t want, const char *name)
{
    if (nargs == want)
        return 0;
    PyErr_Format(PyExc_TypeError, "State.%s takes %zd arguments, got %zd", name, want, nargs);
    return -1;
}

/* -- §2: the nominal state, every IMU sample -------------------------------------------- */

/* predict(acc_b, gyro_b, dt): with ω = ω_m − b_g, f = f_m − b_a (body), a = R f + g:
 * p += (v + a dt / 2) dt, v += a dt, q ← q ⊗ Exp(ω dt); the interval's Σ R f dt and Σ ω dt. */
void uwbd_state_predict(PyObject *state, const double acc[3], const double gyro[3], double dt)
{
    State *self = (State *)state;
    double *p = self->p, *v = self->v, *q = self->q, *bg = self->bg, *ba = self->ba;
    double wx = (gyro[0] - bg[0]) * dt, wy = (gyro[1] - bg[1]) * dt, wz = (gyro[2] - bg[2]) * dt;
    double fx = acc[0] - ba[0], fy = acc[1] - ba[1], fz = acc[2] - ba[2];
    double R[3][3];
    uwbd_quat_to_matrix(q, R); /* before the attitude step: f was measured over dt */
    double ax = R[0][0] * fx + R[0][1] * fy + R[0][2] * fz;
    double ay = R[1][0] * fx + R[1][1] * fy + R[1][2] * fz;
    double az = R[2][0] * fx + R[2][1] * fy + R[2][2] * fz;
    self->sum_fn[0] += ax * dt;
    self->sum_fn[1] += ay * dt;
    self->sum_fn[2] += az * dt;
    self->sum_w[0] += wx;
    self->sum_w[1] += wy;
    self->sum_w[2] += wz;
    self->T += dt;
    az -= self->gravity;
    p[0] += (v[0] + 0.5 * ax * dt) * dt;
    p[1] += (v[1] + 0.5 * ay * dt) * dt;
    p[2] += (v[2] + 0.5 * az * dt) * dt;
    v[0] += ax * dt;
    v[1] += ay * dt;
    v[2] += az * dt;
    double qn[4];
    uwbd_turned(q, wx, wy, wz, qn);
    memcpy(q, qn, sizeof qn);
}

static PyObject *state_predict(State *self, PyObject *const *args, Py_ssize_t nargs)
{
    double acc[3], gyro[3];
    if (check_args(nargs, 3, "predict") || uwbd_get_vec(args[0], acc, 3, "acc_b") ||
        uwbd_get_vec(args[1], gyro, 3, "gyro_b"))
        return NULL;
    double dt = PyFloat_AsDouble(args[2]);
    if (dt == -1.0 && PyErr_Occurred())
        return NULL;
    uwbd_state_predict((PyObject *)self, acc, gyro, dt);
    Py_RETURN_NONE;
}

/* -- §3: the covariance, once per update interval --------------------------------------- */

/* The columns of each row of M (15×15) that are not zero, in order, and how many. */
static void nonzeros(const double M[N_CORE][N_CORE], int nz[N_CORE][N_CORE], int count[N_CORE])
{
    for (int i = 0; i < N_CORE; i++) {
        count[i] = 0;
        for (int k = 0; k < N_CORE; k++)
            if (M[i][k] != 0.0)
                nz[i][count[i]++] = k;
    }
}

/* The Gauss–Markov states' decays over T: φ = e^(−T/τ), one per state (phi: n_markov). */
static void markov_decays(const State *self, double T, double *phi)
{
    for (Py_ssize_t a = 0; a < self->n_markov; a++)
        phi[a] = exp(-T / self->markov_tau[a]);
}

/* Their step on one filter's covariance P and offsets x (the nominal b_r, or a sub-filter's
 * d_k, both indexed by column): x ← φ x, P ← φ P φ on their rows and columns, plus
 * σ² (1 − φ²) on the diagonal. */
static void markov_apply(const State *self, double *P, double *x, const double *phi)
{
    Py_ssize_t n = self->n;
    for (Py_ssize_t a = 0; a < self->n_markov; a++) {
        Py_ssize_t c = self->markov_cols[a];
        for (Py_ssize_t j = 0; j < n; j++)
            P[c * n + j] *= phi[a];
        for (Py_ssize_t i = 0; i < n; i++)
            P[i * n + c] *= phi[a];
        P[c * n + c] += self->markov_var[a] * (1.0 - phi[a] * phi[a]);
        x[c] *= phi[a];
    }
}

/* The Gauss–Markov step over T on the main filter (the epoch's decays follow when kept)
 * and on every sub-filter of the bank. */
static void markov_step(State *self, double T)
{
    if (self->n_markov == 0)
        return;
    Py_ssize_t n = self->n;
    double *phi = self->work + n * n; /* (propagate's rows use only the first 15 n) */
    markov_decays(self, T, phi);
    self->epoch_propagated = 1;
    markov_apply(self, self->P, self->br - N_CORE, phi);
    if (self->keep_transition)
        for (Py_ssize_t a = 0; a < self->n_markov; a++)
            self->decay_epoch[self->markov_cols[a] - N_CORE] *= phi[a];
    for (Py_ssize_t k = 0; k < self->bank; k++)
        markov_apply(self, self->bank_P + k * n * n, self->bank_d + k * n, phi);
}

/* P[:15, :] ← Φ P[:15, :], then P[:, :15] ← P[:, :15] Φᵀ, along rows, over Φ's nonzero
 * terms (nz, count); rows: 15 n doubles of scratch. */
static void phi_apply(double *P, Py_ssize_t n, const double Phi[N_CORE][N_CORE],
                      const int nz[N_CORE][N_CORE], const int count[N_CORE], double *rows)
{
    for (int i = 0; i < N_CORE; i++) {
        double *restrict out = rows + i * n;
        for (Py_ssize_t j = 0; j < n; j++)
            out[j] = 0.0;
        for (int c = 0; c < count[i]; c++) {
            const double g = Phi[i][nz[i][c]], *restrict in = P + nz[i][c] * n;
            for (Py_ssize_t j = 0; j < n; j++)
                out[j] += g * in[j];
        }
    }
    memcpy(P, rows, sizeof(double) * N_CORE * n);
    for (int j = 0; j < N_CORE; j++) {
        double *restrict out = rows + j * n;
        for (Py_ssize_t i = 0; i < n; i++)
            out[i] = 0.0;
        for (int c = 0; c < count[j]; c++) {
            const int k = nz[j][c];
            const double g = Phi[j][k];
            for (Py_ssize_t i = 0; i < n; i++)
                out[i] += P[i * n + k] * g;
        }
    }
    for (Py_ssize_t i = 0; i < n; i++)
        for (int j = 0; j < N_CORE; j++)
            P[i * n + j] = rows[j * n + i];
}

/* propagate(): F from the interval's mean specific force and rate, Φ = I + A + A²/2 with
 * A = F T on the core 15 states, P ← Φ P Φᵀ + diag(q_rate) T, the Gauss–Markov step,
 * P symmetrised; Φ_epoch ← Φ Φ_epoch when kept; the interval starts anew. */
void uwbd_state_propagate(PyObject *state)
{
    State *self = (State *)state;
    double T = self->T;
    if (!(T > 0.0))
        return;
    Py_ssize_t n = self->n;
    double *P = self->P;
    for (int i = 0; i < 3; i++)
        self->dv_epoch[i] += self->sum_fn[i];
    self->epoch_propagated = 1;
    double R[3][3];
    uwbd_quat_to_matrix(self->q, R);
    double f[3], w[3];
    for (int i = 0; i < 3; i++) {
        f[i] = self->sum_fn[i] / T;
        w[i] = self->sum_w[i] / T;
    }
    /* A = F T: P_V = I, V_TH = −[f]× R, V_BA = −R, TH_TH = −[ω]×, TH_BG = −I */
    double A[N_CORE][N_CORE];
    memset(A, 0, sizeof A);
    double sk[3][3] = {{0, -f[2], f[1]}, {f[2], 0, -f[0]}, {-f[1], f[0], 0}};
    double skw[3][3] = {{0, -w[2], w[1]}, {w[2], 0, -w[0]}, {-w[1], w[0], 0}};
    for (int i = 0; i < 3; i++) {
        A[i][3 + i] = T;
        A[TH0 + i][9 + i] = -T;
        for (int j = 0; j < 3; j++) {
            double s = 0.0;
            for (int k = 0; k < 3; k++)
                s += sk[i][k] * R[k][j];
            A[3 + i][TH0 + j] = -s * T;
            A[3 + i][12 + j] = -R[i][j] * T;
            A[TH0 + i][TH0 + j] = -skw[i][j] * T;
        }
    }
    /* A and Φ are about half zeros: each product runs over the nonzero terms of a row */
    int nz[N_CORE][N_CORE], count[N_CORE];
    nonzeros(A, nz, count);
    double Phi[N_CORE][N_CORE];
    for (int i = 0; i < N_CORE; i++)
        for (int j = 0; j < N_CORE; j++) {
            double s = 0.0;
            for (int c = 0; c < count[i]; c++)
                s += A[i][nz[i][c]] * A[nz[i][c]][j];
            Phi[i][j] = (i == j ? 1.0 : 0.0) + A[i][j] + 0.5 * s;
        }
    nonzeros(Phi, nz, count);
    if (self->keep_transition) {
        double tmp[N_CORE * N_CORE];
        const double *E = self->Phi_epoch;
        for (int i = 0; i < N_CORE; i++)
            for (int j = 0; j < N_CORE; j++) {
                double s = 0.0;
                for (int c = 0; c < count[i]; c++)
                    s += Phi[i][nz[i][c]] * E[nz[i][c] * N_CORE + j];
                tmp[i * N_CORE + j] = s;
            }
        memcpy(self->Phi_epoch, tmp, sizeof tmp);
    }
    double *rows = self->work;
    phi_apply(P, n, Phi, nz, count, rows);
    for (Py_ssize_t i = 0; i < n; i++)
        P[i * n + i] += self->q_rate[i] * T;
    for (Py_ssize_t k = 0; k < self->bank; k++) { /* the sub-filters: the same Φ and Q */
        double *Pk = self->bank_P + k * n * n, *d = self->bank_d + k * n, dc[N_CORE];
        phi_apply(Pk, n, Phi, nz, count, rows);
        for (Py_ssize_t i = 0; i < n; i++)
            Pk[i * n + i] += self->q_rate[i] * T;
        for (int i = 0; i < N_CORE; i++) {
            double s = 0.0;
            for (int c = 0; c < count[i]; c++)
                s += Phi[i][nz[i][c]] * d[nz[i][c]];
            dc[i] = s;
        }
        memcpy(d, dc, sizeof dc);
    }
    markov_step(self, T);
    uwbd_symmetrise(P, n);
    for (Py_ssize_t k = 0; k < self->bank; k++)
        uwbd_symmetrise(self->bank_P + k * n * n, n);
    self->T = 0.0;
    memset(self->sum_fn, 0, sizeof self->sum_fn);
    memset(self->sum_w, 0, sizeof self->sum_w);
}

double uwbd_state_interval(PyObject *state) { return ((State *)state)->T; }

static PyObject *state_propagate(State *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)args;
    if (check_args(nargs, 0, "propagate"))
        return NULL;
    uwbd_state_propagate((PyObject *)self);
    Py_RETURN_NONE;
}

/* take_epoch(with_phi) -> (Φ_core (225 floats) or None, decays (m) or None, Σ R f Δt):
 * since the last call, the product of every propagation's Φ and the INS's own velocity
 * change; both start anew. */
/* The epoch's Δv, Φ and decays start anew (take_epoch, after it has read them). */
static void epoch_restart(State *self)
{
    memset(self->dv_epoch, 0, sizeof self->dv_epoch);
    if (self->epoch_propagated) {
        self->epoch_propagated = 0;
        if (self->keep_transition) {
            set_identity(self->Phi_epoch, N_CORE);
            for (Py_ssize_t a = 0; a < self->m; a++)
                self->decay_epoch[a] = 1.0;
        }
    }
}

static PyObject *state_take_epoch(State *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (check_args(nargs, 1, "take_epoch"))
        return NULL;
    int with_phi = PyObject_IsTrue(args[0]);
    if (with_phi < 0)
        return NULL;
    if (with_phi && !self->keep_transition) {
        PyErr_SetString(PyExc_RuntimeError, "take_epoch(with_phi=True) with keep_transition off");
        return NULL;
    }
    PyObject *phi = with_phi ? uwbd_floats(self->Phi_epoch, N_CORE * N_CORE, 0) : Py_NewRef(Py_None);
    PyObject *decay = with_phi ? uwbd_floats(self->decay_epoch, self->m, 0) : Py_NewRef(Py_None);
    PyObject *dv = uwbd_floats(self->dv_epoch, 3, 0);
    if (phi == NULL || decay == NULL || dv == NULL) {
        Py_XDECREF(phi);
        Py_XDECREF(decay);
        Py_XDECREF(dv);
        return NULL;
    }
    epoch_restart(self);
    return Py_BuildValue("(NNN)", phi, decay, dv);
}

/* coast's covariance step on one filter's P before the Gauss–Markov step: Φ = [[I, dt I],
 * [0, I]] on (δp, δv), white acceleration of variance qa on them, the random walks. */
static void coast_P(const State *self, double *P, double dt, double qa)
{
    Py_ssize_t n = self->n;
    for (int i = 0; i < 3; i++)
        for (Py_ssize_t j = 0; j < n; j++)
            P[i * n + j] += dt * P[(3 + i) * n + j];
    for (Py_ssize_t i = 0; i < n; i++)
        for (int j = 0; j < 3; j++)
            P[i * n + j] += dt * P[i * n + 3 + j];
    for (int i = 0; i < 3; i++) {
        P[i * n + i] += qa * (dt * dt * dt) / 3;
        P[i * n + 3 + i] += qa * (dt * dt) / 2;
        P[(3 + i) * n + i] += qa * (dt * dt) / 2;
        P[(3 + i) * n + 3 + i] += qa * dt;
    }
    for (Py_ssize_t i = N_CORE; i < n; i++)
        P[i * n + i] += self->q_rate[i] * dt;
}

/* coast(dt, accel_sigma, yaw_rate_sigma, tilt_rate_sigma): no IMU, constant velocity:
 * p += v dt; Φ = [[I, dt I], [0, I]] on (δp, δv); white acceleration on (δp, δv); the
 * range-model random walks and Gauss–Markov decays; the attitude's σ grows about the
 * vertical at the yaw rate, about the horizontal at the tilt rate. */
static PyObject *state_coast(State *self, PyObject *const *args, Py_ssize_t nargs)
{
    double a[4];
    if (check_args(nargs, 4, "coast"))
        return NULL;
    for (int i = 0; i < 4; i++)
        if ((a[i] = PyFloat_AsDouble(args[i])) == -1.0 && PyErr_Occurred())
            return NULL;
    double dt = a[0], qa = a[1] * a[1], yaw2 = a[2] * a[2], tilt2 = a[3] * a[3];
    Py_ssize_t n = self->n;
    for (int i = 0; i < 3; i++)
        self->p[i] += self->v[i] * dt;
    double R[3][3];
    uwbd_quat_to_matrix(self->q, R);
    coast_P(self, self->P, dt, qa);
    for (Py_ssize_t k = 0; k < self->bank; k++) {
        double *d = self->bank_d + k * n;
        for (int i = 0; i < 3; i++)
            d[i] += dt * d[3 + i];
        coast_P(self, self->bank_P + k * n * n, dt, qa);
    }
    markov_step(self, dt);
    const double *up = R[2]; /* the navigation z axis in body axes (Rᵀ e_z) */
    for (Py_ssize_t k = -1; k < self->bank; k++) {
        double *P = k < 0 ? self->P : self->bank_P + k * n * n;
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++)
                P[(TH0 + i) * n + TH0 + j] += (yaw2 - tilt2) * dt * (up[i] * up[j]) +
                                              (i == j ? tilt2 * dt : 0.0);
        uwbd_symmetrise(P, n);
    }
    Py_RETURN_NONE;
}

/* -- §5: measurement updates ------------------------------------------------------------ */

/* After rows fused on the copy in work (with dx): the nominal state corrected by dx, P
 * symmetrised and reset by G = I but I − ½[δθ]× on the attitude, then taken. */
static void inject(State *self, const double *Pw, const double *dx)
{
    Py_ssize_t n = self->n;
    for (int i = 0; i < 3; i++) {
        self->p[i] += dx[i];
        self->v[i] += dx[3 + i];
        self->bg[i] += dx[9 + i];
        self->ba[i] += dx[12 + i];
    }
    for (Py_ssize_t a = N_CORE; a < n; a++)
        self->br[a - N_CORE] += dx[a];
    double qn[4];
    uwbd_turned(self->q, dx[TH0], dx[TH0 + 1], dx[TH0 + 2], qn);
    memcpy(self->q, qn, sizeof qn);
    memcpy(self->P, Pw, sizeof(double) * n * n);
    uwbd_symmetrise(self->P, n);
    double G[3][3] = {{1.0, 0.5 * dx[TH0 + 2], -0.5 * dx[TH0 + 1]},
                      {-0.5 * dx[TH0 + 2], 1.0, 0.5 * dx[TH0]},
                      {0.5 * dx[TH0 + 1], -0.5 * dx[TH0], 1.0}};
    uwbd_transform_attitude(self->P, n, G);
    for (Py_ssize_t k = 0; k < self->bank; k++) {
        double *Pk = self->bank_P + k * n * n;
        uwbd_symmetrise(Pk, n);
        uwbd_transform_attitude(Pk, n, G);
    }
    memcpy(self->last_dx, dx, sizeof(double) * n);
}

/* The rows (H m×n, y, R) fused on a copy of P; injected when any row was fused. With a
 * bank, each sub-filter takes the same rows with the main filter's weights but those of
 * its anchor (row_anchor: each row's anchor, −1 for none), from its
 * offset d_k; then d_k ← d_k − δx (the nominal state moved by δx) and P_k is reset by the
 * main filter's G. */
static PyObject *fuse_rows(State *self, const double *H, const double *y, const double *Rv,
                           Py_ssize_t m, PyObject *decide, Py_ssize_t c0, Py_ssize_t c1,
                           const long long *row_anchor)
{
    UwbdRowPolicy policy;
    int got = uwbd_get_decide(decide, &policy);
    if (got < 0)
        return NULL;
    Py_ssize_t n = self->n;
    double *Pw = self->work, *dx = Pw + n * n, *scratch = dx + n;
    double *weights = NULL;
    if (self->bank && (weights = PyMem_Malloc(sizeof(double) * (size_t)(m + 1))) == NULL)
        return PyErr_NoMemory();
    memcpy(Pw, self->P, sizeof(double) * n * n);
    memset(dx, 0, sizeof(double) * n);
    int fused;
    PyObject *rows = uwbd_scalar_rows(Pw, dx, n, H, y, Rv, m, decide, got ? &policy : NULL,
                                      c0, c1, scratch, &fused, weights);
    if (rows != NULL && fused) {
        for (Py_ssize_t k = 0; k < self->bank; k++) {
            double *Pk = self->bank_P + k * n * n, *d = self->bank_d + k * n;
            uwbd_bank_rows(Pk, d, n, H, y, Rv, m, weights, row_anchor, self->bank_anchor[k],
                           c0, c1, scratch);
            for (Py_ssize_t a = 0; a < n; a++)
                d[a] -= dx[a];
        }
        inject(self, Pw, dx);
    }
    PyMem_Free(weights);
    return rows;
}

static int considered(PyObject *const *args, Py_ssize_t n, Py_ssize_t *c0, Py_ssize_t *c1)
{
    *c0 = PyLong_AsSsize_t(args[0]);
    *c1 = PyLong_AsSsize_t(args[1]);
    if (PyErr_Occurred())
        return -1;
    if (*c0 < 0 || *c1 > n || *c0 > *c1) {
        PyErr_SetString(PyExc_ValueError, "considered states: 0 <= c0 <= c1 <= n");
        return -1;
    }
    return 0;
}

/* Rows (H m×n, y m, R m) as buffers in view[0..2] (y, H, R), m from y: 0, or -1 with
 * every buffer released. */
static int get_rows(PyObject *H, PyObject *y, PyObject *R, Py_ssize_t n, Py_buffer view[3],
                    Py_ssize_t *m, const char *const names[3])
{
    if (uwbd_get_doubles(y, &view[0], -1, 0, names[0]) < 0)
        return -1;
    *m = view[0].len / 8;
    if (uwbd_get_doubles(H, &view[1], *m * n, 0, names[1]) < 0) {
        PyBuffer_Release(&view[0]);
        return -1;
    }
    if (uwbd_get_doubles(R, &view[2], *m, 0, names[2]) < 0) {
        PyBuffer_Release(&view[0]);
        PyBuffer_Release(&view[1]);
        return -1;
    }
    return 0;
}

static void release_rows(Py_buffer view[3])
{
    for (int i = 0; i < 3; i++)
        PyBuffer_Release(&view[i]);
}

/* Each row's anchor, for the bank: the first rows' from ids (a sequence of ints, or None:
 * no row has one), the rest −1; a new array of m (free with PyMem_Free), or NULL with an
 * error set. */
static long long *row_anchors(PyObject *ids, Py_ssize_t m)
{
    long long *out = PyMem_Malloc(sizeof(long long) * (size_t)(m + 1));
    if (out == NULL)
        return (long long *)PyErr_NoMemory();
    for (Py_ssize_t i = 0; i < m; i++)
        out[i] = -1;
    if (ids == Py_None)
        return out;
    PyObject *seq = PySequence_Fast(ids, "anchor ids: a sequence of ints or None");
    if (seq == NULL || PySequence_Fast_GET_SIZE(seq) > m) {
        if (seq != NULL)
            PyErr_SetString(PyExc_ValueError, "anchor ids: at most one per row");
        Py_XDECREF(seq);
        PyMem_Free(out);
        return NULL;
    }
    for (Py_ssize_t i = 0; i < PySequence_Fast_GET_SIZE(seq); i++)
        out[i] = PyLong_AsLongLong(PySequence_Fast_GET_ITEM(seq, i));
    Py_DECREF(seq);
    if (PyErr_Occurred()) {
        PyMem_Free(out);
        return NULL;
    }
    return out;
}

/* update(H, y, R, decide, c0, c1, ids) -> [(ν, S, w, numerical)]: the rows H (m×n) with
 * residuals y at the prior and variances R fused one scalar at a time (§5), the weights
 * by `decide` (a RowPolicy tuple, or a callable called back per row), states [c0, c1)
 * considered (not corrected); then injected and reset. ids: the first rows' anchors, for
 * the bank (None: no row is an anchor's). */
static PyObject *state_update(State *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_ssize_t c0, c1, n = self->n;
    if (check_args(nargs, 7, "update") || considered(args + 4, n, &c0, &c1) < 0)
        return NULL;
    Py_buffer view[3];
    Py_ssize_t m;
    static const char *const names[3] = {"y", "H", "R"};
    if (get_rows(args[0], args[1], args[2], n, view, &m, names) < 0)
        return NULL;
    PyObject *out = NULL;
    long long *anchor = row_anchors(args[6], m);
    if (anchor != NULL)
        out = fuse_rows(self, view[1].buf, view[0].buf, view[2].buf, m, args[3], c0, c1,
                        anchor);
    PyMem_Free(anchor);
    release_rows(view);
    return out;
}

/* The range rows' scratch grown to `need` doubles: 0, or -1 with MemoryError. */
static int rows_room(State *self, Py_ssize_t need)
{
    if (need <= self->rows_cap)
        return 0;
    double *grown = PyMem_Realloc(self->rows, sizeof(double) * (size_t)need);
    if (grown == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    self->rows = grown;
    self->rows_cap = need;
    return 0;
}

/* fuse_ranges' work on numbers: the k range rows (mm_range.c; a range with no line to
 * linearise a zero row, its outcome None), then e extra rows (He e×n, ye, Re), fused as
 * update fuses them; ids: the ranges' anchors. The rows' outcomes, or NULL with an error. */
static PyObject *epoch_rows(State *self, const double lever[3], const double *anchors,
                            const double *ranges, const double *var, Py_ssize_t k,
                            PyObject *columns, PyObject *lever_columns, const double *He,
                            const double *ye, const double *Re, Py_ssize_t e,
                            PyObject *decide, Py_ssize_t c0, Py_ssize_t c1, PyObject *ids)
{
    Py_ssize_t n = self->n, m = k + e;
    if (rows_room(self, m * n + 2 * m + k) < 0)
        return NULL;
    double *H = self->rows, *y = H + m * n, *R = y + m, *dist = R + m;
    memset(H, 0, sizeof(double) * (size_t)(k * n));
    if (uwbd_range_rows(self->p, self->q, lever, anchors, ranges, k, self->br, n, columns,
                        lever_columns, H, y, dist) < 0)
        return NULL;
    memcpy(R, var, sizeof(double) * k);
    int lineless = 0; /* a range with no line: a zero row, which changes nothing */
    for (Py_ssize_t a = 0; a < k; a++)
        if (!UWBD_LINE_OF(dist[a])) {
            memset(H + a * n, 0, sizeof(double) * n);
            y[a] = 0.0;
            lineless = 1;
        }
    if (e) {
        memcpy(H + k * n, He, sizeof(double) * e * n);
        memcpy(y + k, ye, sizeof(double) * e);
        memcpy(R + k, Re, sizeof(double) * e);
    }
    long long *anchor = row_anchors(ids, m); /* (ids: the ranges' anchors) */
    if (anchor == NULL)
        return NULL;
    PyObject *out = fuse_rows(self, H, y, R, m, decide, c0, c1, anchor);
    PyMem_Free(anchor);
    if (out != NULL && lineless) /* and its row is None */
        for (Py_ssize_t a = 0; a < k; a++)
            if (!UWBD_LINE_OF(dist[a]))
                PyList_SetItem(out, a, Py_NewRef(Py_None));
    return out;
}

/* fuse_ranges(lever, anchors (k×3), ranges (k), var (k), columns, lever_columns, H_extra,
 *             y_extra, R_extra, decide, c0, c1, ids) -> rows
 * A tight epoch: the range rows (mm_range.c), then the extra rows (ZUPT, NHC, height), as
 * update fuses them; one row per range and extra row, in order. A range whose antenna is
 * within 1 mm of its anchor, or whose distance is not a number, has no line to linearise:
 * it is left out of the update (a zero row: exactly nothing changes) and its row is None
 * (the reference, range_rows, drops it). */
static PyObject *state_fuse_ranges(State *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_ssize_t c0, c1, n = self->n;
    double lever[3];
    if (check_args(nargs, 13, "fuse_ranges") || considered(args + 10, n, &c0, &c1) < 0 ||
        uwbd_get_vec(args[0], lever, 3, "lever"))
        return NULL;
    Py_buffer view[3], extra[3]; /* ranges, anchors, var; y, H, R of the extra rows */
    int got = 0, rows = 0;
    PyObject *out = NULL;
    if (uwbd_get_doubles(args[2], &view[0], -1, 0, "ranges") < 0)
        return NULL;
    got = 1;
    Py_ssize_t k = view[0].len / 8, e;
    if (uwbd_get_doubles(args[1], &view[1], 3 * k, 0, "anchors") < 0)
        goto done;
    got = 2;
    if (uwbd_get_doubles(args[3], &view[2], k, 0, "var") < 0)
        goto done;
    got = 3;
    static const char *const names[3] = {"y_extra", "H_extra", "R_extra"};
    if (get_rows(args[6], args[7], args[8], n, extra, &e, names) < 0)
        goto done;
    rows = 1;
    out = epoch_rows(self, lever, view[1].buf, view[0].buf, view[2].buf, k, args[4], args[5],
                     extra[1].buf, extra[0].buf, extra[2].buf, e, args[9], c0, c1, args[12]);
done:
    for (int i = 0; i < got; i++)
        PyBuffer_Release(&view[i]);
    if (rows)
        release_rows(extra);
    return out;
}

static int clamp_P(double *P, Py_ssize_t n, const double *L, double *scale);

/* One range of fuse_period, a (t_ns, anchor id, anchor (3), range, var, columns) tuple
 * (id None: its anchor is left out, the range has no row): the state predicted to its time
 * with the last sample (body axes, ab gb) when later, propagated when the interval reaches
 * min_prop_s, the epoch's sums started anew, its row fused and P clamped (limit). 0 with
 * its outcome in *row (None where it has no line), or -1 with an error. */
static int period_range(State *self, PyObject *item, const double base[3],
                        PyObject *lever_columns, Py_ssize_t lever_at, PyObject *decide,
                        const double *limit, long long *state_ns, const double ab[3],
                        const double gb[3], double min_prop_s, int *clamped, int *predicted,
                        PyObject **row)
{
    double anchor[3], range, var, lever[3];
    if (!PyTuple_Check(item) || PyTuple_GET_SIZE(item) != 6) {
        PyErr_SetString(PyExc_TypeError,
                        "fuse_period: ranges are (t_ns, id, anchor, range, var, columns)");
        return -1;
    }
    long long t_ns = PyLong_AsLongLong(PyTuple_GET_ITEM(item, 0));
    range = PyFloat_AsDouble(PyTuple_GET_ITEM(item, 3));
    var = PyFloat_AsDouble(PyTuple_GET_ITEM(item, 4));
    if (PyErr_Occurred() || uwbd_get_vec(PyTuple_GET_ITEM(item, 2), anchor, 3, "anchor"))
        return -1;
    double dt = (double)(t_ns - *state_ns) / 1e9;
    if (dt > 0) {
        uwbd_state_predict((PyObject *)self, ab, gb, dt);
        *state_ns = t_ns;
        *predicted = 1;
    }
    if (self->T >= min_prop_s)
        uwbd_state_propagate((PyObject *)self);
    epoch_restart(self);
    if (PyTuple_GET_ITEM(item, 1) == Py_None) { /* its anchor left out: no row */
        *row = Py_NewRef(Py_None);
        return 0;
    }
    for (int i = 0; i < 3; i++)
        lever[i] = base[i] + (lever_at >= 0 ? self->br[lever_at + i] : 0.0);
    PyObject *columns = PyTuple_Pack(1, PyTuple_GET_ITEM(item, 5));
    PyObject *ids = columns ? PyTuple_Pack(1, PyTuple_GET_ITEM(item, 1)) : NULL;
    PyObject *out = ids ? epoch_rows(self, lever, anchor, &range, &var, 1, columns,
                                     lever_columns, NULL, NULL, NULL, 0, decide, 0, 0, ids)
                        : NULL;
    Py_XDECREF(columns);
    Py_XDECREF(ids);
    if (out == NULL)
        return -1;
    *row = Py_NewRef(PyList_GET_ITEM(out, 0));
    Py_DECREF(out);
    Py_ssize_t n = self->n;
    *clamped += clamp_P(self->P, n, limit, self->work);
    for (Py_ssize_t k = 0; k < self->bank; k++)
        clamp_P(self->bank_P + k * n * n, n, limit, self->work);
    return 0;
}

/* fuse_period(front, order, samples, ranges, lever, lever_columns, decide, limit, clock,
 *             last_imu)
 *     -> (done, reason, rows, outcomes, last_ns, state_ns, last_imu, clamps, predicted)
 * A pose period's measurements in the order they came (order: one byte per item, b"i" the
 * next of samples, (t_ns, acc, gyro) in sensor axes; b"r" the next of ranges, see
 * period_range; the policy hands only ranges it judged common): a sample through the IMU
 * front (_imu.c: the common sample judged, mapped, integrated), a range predicted to with
 * the last sample, fused (decide: its RowPolicy; lever: the lever arm given, its error
 * states' columns lever_columns added) and P clamped to limit (clamp). clock: (last_ns,
 * state_ns, max_gap_s, propagate_every_s, min_propagate_s): the last sample's time, the
 * state's; last_imu: the last good sample in body axes (6). Stops at the first sample that
 * is not the common one (done: its index; reason: the front's reason when it rejected it,
 * else None); rows: the samples integrated (t_ns, acc_b..., gyro_b...), as the rest window
 * keeps them; outcomes: each range's (ν, S, w, numerical) or None; clamps: how often the
 * main filter's P was clamped; predicted: whether a range moved the state's time. The
 * reference is the policy's own step per item (policy/period.py on the pure-Python core). */
static PyObject *state_fuse_period(State *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (check_args(nargs, 10, "fuse_period"))
        return NULL;
    if (!PyObject_TypeCheck(args[0], &UwbdImuFrontType) || !PyBytes_Check(args[1]) ||
        !PyList_Check(args[2]) || !PyList_Check(args[3]) || !PyTuple_Check(args[5])) {
        PyErr_SetString(PyExc_TypeError, "fuse_period(front: ImuFront, order: bytes, samples: "
                                         "list, ranges: list, lever, lever_columns: tuple, ...)");
        return NULL;
    }
    double base[3], clock[5], last_imu[6];
    long long last_ns, state_ns;
    if (uwbd_get_vec(args[4], base, 3, "lever") || uwbd_get_vec(args[9], last_imu, 6, "last_imu"))
        return NULL;
    if (!PyTuple_Check(args[8]) || PyTuple_GET_SIZE(args[8]) != 5) {
        PyErr_SetString(PyExc_TypeError, "fuse_period: clock is (last_ns, state_ns, "
                                         "max_gap_s, propagate_every_s, min_propagate_s)");
        return NULL;
    }
    last_ns = PyLong_AsLongLong(PyTuple_GET_ITEM(args[8], 0));
    state_ns = PyLong_AsLongLong(PyTuple_GET_ITEM(args[8], 1));
    for (int i = 2; i < 5; i++)
        clock[i] = PyFloat_AsDouble(PyTuple_GET_ITEM(args[8], i));
    if (PyErr_Occurred())
        return NULL;
    Py_ssize_t lever_at = -1;
    if (PyTuple_GET_SIZE(args[5]) > 0) {
        lever_at = PyLong_AsSsize_t(PyTuple_GET_ITEM(args[5], 0)) - N_CORE;
        if (PyErr_Occurred())
            return NULL;
        if (lever_at < 0 || lever_at + 3 > self->m) {
            PyErr_SetString(PyExc_ValueError, "fuse_period: lever_columns outside b_r");
            return NULL;
        }
    }
    Py_buffer Lb;
    if (uwbd_get_doubles(args[7], &Lb, self->n, 0, "limit") < 0)
        return NULL;
    const char *order = PyBytes_AS_STRING(args[1]);
    Py_ssize_t count = PyBytes_GET_SIZE(args[1]), done = 0, si = 0, ri = 0;
    PyObject *rows = PyList_New(0), *outcomes = PyList_New(0), *reason = Py_None;
    int clamps = 0, predicted = 0;
    if (rows == NULL || outcomes == NULL)
        goto fail;
    for (; done < count; done++) {
        if (order[done] == 'i') {
            if (si >= PyList_GET_SIZE(args[2]))
                break;
            double ab[3], gb[3];
            int r = uwbd_front_take(args[0], (PyObject *)self, PyList_GET_ITEM(args[2], si),
                                    &last_ns, &state_ns, clock[2], clock[3], rows, ab, gb);
            if (r == -2)
                goto fail;
            if (r != 0) {
                if (r > 0)
                    reason = uwbd_front_reason(args[0], r);
                break;
            }
            memcpy(last_imu, ab, sizeof ab);
            memcpy(last_imu + 3, gb, sizeof gb);
            si++;
        } else {
            if (ri >= PyList_GET_SIZE(args[3]))
                break;
            PyObject *row = NULL;
            if (period_range(self, PyList_GET_ITEM(args[3], ri), base, args[5], lever_at, args[6],
                             Lb.buf, &state_ns, last_imu, last_imu + 3, clock[4], &clamps,
                             &predicted, &row) < 0)
                goto fail;
            int appended = PyList_Append(outcomes, row);
            Py_DECREF(row);
            if (appended < 0)
                goto fail;
            ri++;
        }
    }
    PyBuffer_Release(&Lb);
    PyObject *imu = uwbd_floats(last_imu, 6, 0);
    if (imu == NULL) {
        Py_DECREF(rows);
        Py_DECREF(outcomes);
        return NULL;
    }
    return Py_BuildValue("(nONNLLNiO)", done, reason, rows, outcomes, last_ns, state_ns, imu,
                         clamps, predicted ? Py_True : Py_False);
fail:
    PyBuffer_Release(&Lb);
    Py_XDECREF(rows);
    Py_XDECREF(outcomes);
    return NULL;
}

/* range_check(lever, anchors (k×3), ranges (k), var (k) or None, columns, out)
 *     -> None, or whether the single-fault estimates were made
 * The epoch's ranges before their update, for the installation checks (§6): into out, the
 * unit vectors anchor → antenna U (k×3), the innovations y (k) and, with var, Baarda's
 * single-fault estimate of each range b (k) and its weight d (k) from S = H P Hᵀ + diag(var)
 * (_checks.c; False when S is singular). None, out untouched, when an antenna is within
 * 1 mm of an anchor or a distance is not a number (the reference, measurements.range_check,
 * has no line to linearise there either). Nothing of the state changes. */
static PyObject *state_range_check(State *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_ssize_t n = self->n;
    double lever[3];
    if (check_args(nargs, 6, "range_check") || uwbd_get_vec(args[0], lever, 3, "lever"))
        return NULL;
    Py_buffer view[4]; /* ranges, anchors, out, var */
    int got = 0, with_var = args[3] != Py_None;
    PyObject *result = NULL;
    if (uwbd_get_doubles(args[2], &view[0], -1, 0, "ranges") < 0)
        return NULL;
    got = 1;
    Py_ssize_t k = view[0].len / 8;
    if (uwbd_get_doubles(args[1], &view[1], 3 * k, 0, "anchors") < 0)
        goto done;
    got = 2;
    if (uwbd_get_doubles(args[5], &view[2], CHECK_PER_RANGE * k, 1, "out") < 0)
        goto done;
    got = 3;
    if (with_var) {
        if (uwbd_get_doubles(args[3], &view[3], k, 0, "var") < 0)
            goto done;
        got = 4;
    }
    /* H (k×n), y (k), H P (k×n), S (k×k), the inverse's k×k, the distances (k) */
    if (rows_room(self, 2 * k * n + 2 * k + 2 * k * k) < 0)
        goto done;
    double *H = self->rows, *y = H + k * n, *HP = y + k, *S = HP + k * n, *Si = S + k * k;
    double *dist = Si + k * k, *out = view[2].buf;
    memset(H, 0, sizeof(double) * (size_t)(k * n));
    if (uwbd_range_rows(self->p, self->q, lever, view[1].buf, view[0].buf, k, self->br, n,
                        args[4], NULL, H, y, dist) < 0)
        goto done;
    for (Py_ssize_t a = 0; a < k; a++)
        if (!UWBD_LINE_OF(dist[a])) {
            result = Py_NewRef(Py_None);
            goto done;
        }
    for (Py_ssize_t a = 0; a < k; a++) { /* the blocks of layout.RANGE_CHECK */
        memcpy(out + CHECK_U * k + 3 * a, H + a * n, sizeof(double) * 3);
        out[CHECK_Y * k + a] = y[a];
    }
    int made = 0;
    if (with_var) {
        const double *var = view[3].buf, *P = self->P;
        for (Py_ssize_t a = 0; a < k; a++)
            for (Py_ssize_t j = 0; j < n; j++) {
                double s = 0.0;
                for (Py_ssize_t i = 0; i < n; i++)
                    s += H[a * n + i] * P[i * n + j];
                HP[a * n + j] = s;
            }
        for (Py_ssize_t a = 0; a < k; a++)
            for (Py_ssize_t c = 0; c < k; c++) {
                double s = 0.0;
                for (Py_ssize_t j = 0; j < n; j++)
                    s += HP[a * n + j] * H[c * n + j];
                S[a * k + c] = s + (a == c ? var[a] : 0.0);
            }
        made = uwbd_single_faults(S, y, k, out + CHECK_B * k, out + CHECK_D * k, Si) == 0;
    }
    result = PyBool_FromLong(made);
done:
    for (int i = 0; i < got; i++)
        PyBuffer_Release(&view[i]);
    return result;
}

/* -- §6: the heading's turn, the covariance's repairs ----------------------------------- */

/* rotate_heading(dpsi, yaw_sigma): q turned by dpsi about the navigation z axis; the
 * heading's variance restarted at yaw_sigma², uncorrelated; roll and pitch kept (the
 * attitude error turned into the navigation frame for it, and back). The same on each
 * sub-filter of the bank, whose heading offset is dropped (the heading is the aligner's,
 * for all): the rest of what it knows, without its anchor, is kept. */
static PyObject *state_rotate_heading(State *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (check_args(nargs, 2, "rotate_heading"))
        return NULL;
    double dpsi = PyFloat_AsDouble(args[0]), sigma = PyFloat_AsDouble(args[1]);
    if (PyErr_Occurred())
        return NULL;
    double c = cos(dpsi / 2), s = sin(dpsi / 2), *q = self->q;
    double w = q[0], x = q[1], y = q[2], z = q[3];
    double t[4] = {c * w - s * z, c * x - s * y, c * y + s * x, c * z + s * w};
    double norm = sqrt(t[0] * t[0] + t[1] * t[1] + t[2] * t[2] + t[3] * t[3]);
    for (int i = 0; i < 4; i++)
        q[i] = t[i] / norm;
    double R[3][3], Rt[3][3];
    uwbd_quat_to_matrix(q, R);
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            Rt[i][j] = R[j][i];
    Py_ssize_t n = self->n, k = TH0 + 2; /* the navigation-frame yaw error */
    for (Py_ssize_t b = -1; b < self->bank; b++) { /* the main filter, then each sub-filter */
        double *P = b < 0 ? self->P : self->bank_P + b * n * n;
        uwbd_transform_attitude(P, n, R);
        for (Py_ssize_t j = 0; j < n; j++)
            P[k * n + j] = P[j * n + k] = 0.0;
        P[k * n + k] = sigma * sigma;
        uwbd_transform_attitude(P, n, Rt);
        if (b < 0)
            continue;
        double *th = self->bank_d + b * n + TH0; /* its heading offset dropped: R δθ's z */
        double yaw = R[2][0] * th[0] + R[2][1] * th[1] + R[2][2] * th[2];
        for (int i = 0; i < 3; i++)
            th[i] -= Rt[i][2] * yaw;
    }
    Py_RETURN_NONE;
}

/* One filter's P (n×n) with every variance within its limit L and none negative (scale:
 * n doubles of scratch); 1 when anything was clamped. */
static int clamp_P(double *P, Py_ssize_t n, const double *L, double *scale)
{
    int out = 0;
    for (Py_ssize_t i = 0; i < n && !out; i++)
        out = P[i * n + i] > L[i] || P[i * n + i] < 0.0; /* (NaN is neither) */
    if (out) {
        for (Py_ssize_t i = 0; i < n; i++) {
            double d = P[i * n + i];
            double r = L[i] / (d > 1e-300 ? d : 1e-300);
            scale[i] = sqrt(r < 1.0 ? r : 1.0);
        }
        for (Py_ssize_t i = 0; i < n; i++)
            for (Py_ssize_t j = 0; j < n; j++)
                P[i * n + j] = P[i * n + j] * scale[i] * scale[j];
        for (Py_ssize_t i = 0; i < n; i++)
            if (P[i * n + i] < 0.0)
                P[i * n + i] = 1e-9;
    }
    return out;
}

/* clamp(limit) -> bool: every variance within its limit (n variances) and none negative;
 * a row and its column scaled by √(limit/P_ii), which keeps P positive semi-definite;
 * True when anything was clamped (the main filter's; each sub-filter's is clamped on its
 * own). */
static PyObject *state_clamp(State *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_ssize_t n = self->n;
    Py_buffer Lb;
    if (check_args(nargs, 1, "clamp") || uwbd_get_doubles(args[0], &Lb, n, 0, "limit") < 0)
        return NULL;
    int out = clamp_P(self->P, n, Lb.buf, self->work);
    for (Py_ssize_t k = 0; k < self->bank; k++)
        clamp_P(self->bank_P + k * n * n, n, Lb.buf, self->work);
    PyBuffer_Release(&Lb);
    return PyBool_FromLong(out);
}

/* widen(start, stop, factor): the σ of the states [start, stop) (and their correlations'
 * share) times factor. */
static PyObject *state_widen(State *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_ssize_t c0, c1, n = self->n;
    if (check_args(nargs, 3, "widen") || considered(args, n, &c0, &c1) < 0)
        return NULL;
    double f = PyFloat_AsDouble(args[2]);
    if (f == -1.0 && PyErr_Occurred())
        return NULL;
    for (Py_ssize_t k = -1; k < self->bank; k++) {
        double *P = k < 0 ? self->P : self->bank_P + k * n * n;
        for (Py_ssize_t i = 0; i < n; i++)
            for (Py_ssize_t j = 0; j < n; j++)
                P[i * n + j] = P[i * n + j] * (i >= c0 && i < c1 ? f : 1.0) *
                               (j >= c0 && j < c1 ? f : 1.0);
    }
    Py_RETURN_NONE;
}

/* add_variances(d): P_ii += d_i (n numbers). */
static PyObject *state_add_variances(State *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_ssize_t n = self->n;
    double *d = self->work;
    if (check_args(nargs, 1, "add_variances") || uwbd_get_vec(args[0], d, n, "variances"))
        return NULL;
    for (Py_ssize_t k = -1; k < self->bank; k++) {
        double *P = k < 0 ? self->P : self->bank_P + k * n * n;
        for (Py_ssize_t i = 0; i < n; i++)
            P[i * n + i] += d[i];
    }
    Py_RETURN_NONE;
}

/* set_covariance(P): P taken as given (n×n; a restore); the bank anew. */
static PyObject *state_set_covariance(State *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_ssize_t n = self->n;
    Py_buffer Pb;
    if (check_args(nargs, 1, "set_covariance") ||
        uwbd_get_doubles(args[0], &Pb, n * n, 0, "P") < 0)
        return NULL;
    memcpy(self->P, Pb.buf, sizeof(double) * n * n);
    PyBuffer_Release(&Pb);
    bank_reset(self);
    Py_RETURN_NONE;
}

/* adopt(k): the main filter becomes sub-filter k (an anchor's fault found and excluded,
 * §6): the nominal state corrected by d_k as an update would inject it, P ← P_k reset by
 * its G; then the bank anew. */
static PyObject *state_adopt(State *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (check_args(nargs, 1, "adopt"))
        return NULL;
    Py_ssize_t k = PyLong_AsSsize_t(args[0]), n = self->n;
    if (k == -1 && PyErr_Occurred())
        return NULL;
    if (k < 0 || k >= self->bank) {
        PyErr_Format(PyExc_IndexError, "adopt: sub-filter %zd of %zd", k, self->bank);
        return NULL;
    }
    double *Pw = self->work, *dx = Pw + n * n;
    memcpy(Pw, self->bank_P + k * n * n, sizeof(double) * (size_t)(n * n));
    memcpy(dx, self->bank_d + k * n, sizeof(double) * (size_t)n);
    inject(self, Pw, dx);
    bank_reset(self);
    Py_RETURN_NONE;
}

/* restart(k): sub-filter k alone started anew from the main filter (d_k = 0, P_k = P + its
 * variances): what it learnt before is dropped (the lever member's, at the heading's
 * alignment, before which it soaked up the unknown heading). */
static PyObject *state_restart(State *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (check_args(nargs, 1, "restart"))
        return NULL;
    Py_ssize_t k = PyLong_AsSsize_t(args[0]);
    if (k == -1 && PyErr_Occurred())
        return NULL;
    if (k < 0 || k >= self->bank) {
        PyErr_Format(PyExc_IndexError, "restart: sub-filter %zd of %zd", k, self->bank);
        return NULL;
    }
    member_reset(self, k);
    Py_RETURN_NONE;
}

/* move_to(p, v): the position and velocity set (a position reset to a UWB fix); the bank
 * anew. */
static PyObject *state_move_to(State *self, PyObject *const *args, Py_ssize_t nargs)
{
    double p[3], v[3];
    if (check_args(nargs, 2, "move_to") || uwbd_get_vec(args[0], p, 3, "p") ||
        uwbd_get_vec(args[1], v, 3, "v"))
        return NULL;
    memcpy(self->p, p, sizeof p);
    memcpy(self->v, v, sizeof v);
    bank_reset(self);
    Py_RETURN_NONE;
}

/* -- outputs ---------------------------------------------------------------------------- */

/* pose_numbers(aligned)
 * -> (covariance (36), σ_xy, position (3), velocity (3), xyzw (4)),
 *    or None when a number is not finite
 * The covariance over position and the attitude error turned into the navigation frame,
 * [[Ppp, Ppθ Rᵀ], [R Pθp, R Pθθ Rᵀ]], row-major, made symmetric; while the heading is not
 * aligned its yaw row and column are 0 and its variance π². */
/* σ along the major axis of the horizontal ellipse of a covariance's position block (C,
 * row stride n), 0 where the numbers say less (bank.major_sigma). */
static double major_sigma(const double *C, Py_ssize_t n)
{
    double xx = C[0], xy = C[1], yy = C[n + 1], half = (xx - yy) / 2;
    double m = (xx + yy) / 2 + sqrt(half * half + xy * xy);
    return sqrt(m > 0.0 ? m : 0.0);
}

/* separation_numbers() -> (major σ of P, P_zz, [(major σ and zz of P_k − P, major σ and zz
 * of P_k, |d_k| horizontal, |d_k| vertical)] per sub-filter): the numbers the solution
 * separation judges (checks/separation.py; the reference is bank.separation_numbers). */
static PyObject *state_separation_numbers(State *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)args;
    if (check_args(nargs, 0, "separation_numbers"))
        return NULL;
    Py_ssize_t n = self->n;
    const double *P = self->P;
    PyObject *members = PyList_New(self->bank);
    if (members == NULL)
        return NULL;
    for (Py_ssize_t k = 0; k < self->bank; k++) {
        const double *Pk = self->bank_P + k * n * n, *d = self->bank_d + k * n;
        double D[3 * 3];
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++)
                D[i * 3 + j] = Pk[i * n + j] - P[i * n + j];
        PyObject *row = Py_BuildValue("(dddddd)", major_sigma(D, 3), D[8], major_sigma(Pk, n),
                                      Pk[2 * n + 2], hypot(d[0], d[1]), fabs(d[2]));
        if (row == NULL) {
            Py_DECREF(members);
            return NULL;
        }
        PyList_SET_ITEM(members, k, row);
    }
    return Py_BuildValue("(ddN)", major_sigma(P, n), P[2 * n + 2], members);
}

static PyObject *state_pose_numbers(State *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (check_args(nargs, 1, "pose_numbers"))
        return NULL;
    int aligned = PyObject_IsTrue(args[0]);
    if (aligned < 0)
        return NULL;
    Py_ssize_t n = self->n;
    const double *P = self->P, *q = self->q, *p = self->p, *v = self->v;
    for (int i = 0; i < 9; i++) /* any NaN or inf over (p, v, θ) */
        for (int j = 0; j < 9; j++)
            if (!isfinite(P[i * n + j]))
                Py_RETURN_NONE;
    double R[3][3];
    uwbd_quat_to_matrix(q, R);
    double TP[6][9];
    for (int j = 0; j < 9; j++) {
        for (int i = 0; i < 3; i++)
            TP[i][j] = P[i * n + j];
        for (int i = 0; i < 3; i++)
            TP[3 + i][j] = R[i][0] * P[6 * n + j] + R[i][1] * P[7 * n + j]
                + R[i][2] * P[8 * n + j];
    }
    double M[6][6], cov[36];
    for (int i = 0; i < 6; i++) {
        for (int j = 0; j < 3; j++)
            M[i][j] = TP[i][j];
        for (int j = 0; j < 3; j++)
            M[i][3 + j] = TP[i][6] * R[j][0] + TP[i][7] * R[j][1] + TP[i][8] * R[j][2];
    }
    for (int i = 0; i < 6; i++)
        for (int j = 0; j < 6; j++)
            cov[6 * i + j] = 0.5 * (M[i][j] + M[j][i]);
    if (!aligned) {
        for (int i = 0; i < 6; i++)
            cov[6 * i + 5] = cov[30 + i] = 0.0;
        cov[35] = M_PI * M_PI;
    }
    double s = p[0] + p[1] + p[2] + v[0] + v[1] + v[2] + q[0] + q[1] + q[2] + q[3];
    for (int i = 0; i < 36; i++)
        s += cov[i];
    if (!isfinite(s))
        Py_RETURN_NONE;
    double xy = cov[0] + cov[7];
    double sigma_xy = sqrt(xy > 0.0 ? xy : 0.0);
    const double xyzw[4] = {q[1], q[2], q[3], q[0]};
    return Py_BuildValue("(NdNNN)", uwbd_floats(cov, 36, 0), sigma_xy, uwbd_floats(p, 3, 0),
                         uwbd_floats(v, 3, 0), uwbd_floats(xyzw, 4, 0));
}

/* -- attributes ------------------------------------------------------------------------- */

static PyObject *get_interval(State *self, void *c)
{
    (void)c;
    return PyFloat_FromDouble(self->T);
}

static PyObject *get_n(State *self, void *c)
{
    (void)c;
    return PyLong_FromSsize_t(self->n);
}

static PyObject *get_bank(State *self, void *c)
{
    (void)c;
    PyObject *out = PyTuple_New(self->bank);
    for (Py_ssize_t k = 0; out != NULL && k < self->bank; k++) {
        PyObject *a = PyLong_FromLongLong(self->bank_anchor[k]);
        if (a == NULL)
            Py_CLEAR(out);
        else
            PyTuple_SET_ITEM(out, k, a);
    }
    return out;
}

static PyObject *get_keep(State *self, void *c)
{
    (void)c;
    return PyBool_FromLong(self->keep_transition);
}

static int set_keep(State *self, PyObject *value, void *c)
{
    (void)c;
    int keep = value == NULL ? -1 : PyObject_IsTrue(value);
    if (keep < 0) {
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_TypeError, "keep_transition cannot be deleted");
        return -1;
    }
    self->keep_transition = keep;
    return 0;
}

static PyGetSetDef state_getset[] = {
    {"interval_s", (getter)get_interval, NULL, "Time integrated since the last propagate.",
     NULL},
    {"n", (getter)get_n, NULL, "The error state's size.", NULL},
    {"bank", (getter)get_bank, NULL, "The anchor each sub-filter of the bank leaves out.",
     NULL},
    {"keep_transition", (getter)get_keep, (setter)set_keep,
     "Φ kept over the epoch for take_epoch(with_phi) (smoothing); off, not multiplied.", NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

#define METHOD(name, doc) \
    {#name, (PyCFunction)(void (*)(void))state_##name, METH_FASTCALL, doc}

static PyMethodDef state_methods[] = {
    METHOD(predict, "predict(acc_b, gyro_b, dt): one IMU sample (body axes), §2."),
    METHOD(propagate, "propagate(): P over the interval integrated, §3."),
    METHOD(take_epoch, "take_epoch(with_phi) -> (Φ_core or None, decays or None, Σ R f Δt)."),
    METHOD(coast, "coast(dt, accel_sigma, yaw_rate_sigma, tilt_rate_sigma): no IMU, §3."),
    METHOD(update, "update(H, y, R, decide, c0, c1, ids) -> rows: fused, injected, reset, "
                   "§5."),
    METHOD(fuse_ranges, "fuse_ranges(lever, anchors, ranges, var, columns, lever_columns, H, "
                        "y, R, decide, c0, c1, ids) -> rows: a tight epoch, §4-5."),
    METHOD(fuse_period, "fuse_period(front, order, samples, ranges, lever, lever_columns, "
                        "decide, limit, clock, last_imu) -> (done, reason, rows, outcomes, "
                        "last_ns, state_ns, last_imu, clamps, predicted)."),
    METHOD(range_check, "range_check(lever, anchors, ranges, var, columns, out) -> None or "
                        "bool: U, y and single-fault estimates for the checks, §6."),
    METHOD(rotate_heading, "rotate_heading(dpsi, yaw_sigma): the coarse heading's turn."),
    METHOD(clamp, "clamp(limit) -> bool: every variance within its limit."),
    METHOD(widen, "widen(start, stop, factor): those states' sigma times factor."),
    METHOD(add_variances, "add_variances(d): P_ii += d_i."),
    METHOD(set_covariance, "set_covariance(P): P restored."),
    METHOD(move_to, "move_to(p, v): position and velocity set."),
    METHOD(adopt, "adopt(k): the main filter becomes sub-filter k; the bank anew."),
    METHOD(restart, "restart(k): sub-filter k alone started anew from the main filter."),
    METHOD(separation_numbers, "separation_numbers() -> (major σ, zz of P, [per sub-filter: "
                               "major σ, zz of P_k − P and of P_k, |d_k| h and v])."),
    METHOD(pose_numbers, "pose_numbers(aligned) -> the pose's numbers or None."),
    {NULL, NULL, 0, NULL},
};

PyTypeObject UwbdStateType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "uwbd.fusion.core._core.State",
    .tp_doc = "The error-state EKF's numbers and the operations on them (docs/ekf.md); "
              "read-only through the buffer protocol: p v q b_g b_a b_r P last_dx, then the "
              "bank's d_k and P_k.",
    .tp_basicsize = sizeof(State),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)state_init,
    .tp_dealloc = (destructor)state_dealloc,
    .tp_as_buffer = &state_as_buffer,
    .tp_methods = state_methods,
    .tp_getset = state_getset,
};
