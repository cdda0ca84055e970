/* The numerics of one iteration of the fast shooting SQP (saml_ros/core/mpc/shooting/sqp.py) in C.
 *
 * Loaded with ctypes by saml_ros/core/mpc/shooting/native.py, which builds it with the system's C compiler
 * (-O3 -ffp-contract=off: no fused multiply-adds, so the quadrotor step below rounds exactly as
 * QuadrotorBaseNP._step_floats does). The Python solver keeps its control flow (Levenberg-Marquardt weight,
 * penalty, convergence) and the QP (DAQP); this file does what it spent most of an iteration on in ~25 numpy
 * calls: the model's Jacobians along the plan, the condensed sensitivities, the smoothed Euclidean cost model,
 * the constraint rows, the merit and the line search's rollouts.
 *
 * The prediction model is y = f_hat(x, u) + clip(phi(x, u), -bound, bound) with f_hat the quadrotor's base model
 * (or none: y = phi) and phi a PReLU network with the input normalisation and output scale folded into its first
 * and last layers (NumpyMLP's weights). All arrays are float64, row-major. */
#include <math.h>
#include <string.h>

#define MAXW 512   /* widest layer; also the most controls in a plan (T m) */
#define MAXL 8     /* layers */
#define MAXZ 48    /* n + m */

typedef struct {
    long n, m;          /* state and control sizes */
    long base;          /* 1: the quadrotor's f_hat (n = 13, m = 4); 0: none */
    long layers;        /* weight matrices of phi; 0: no network */
    long has_bound;     /* clip phi to +-bound */
    double dt, mass, g;
    double inertia[3];  /* diagonal inertia (kg m^2) */
    double jinv[3];     /* dt / inertia, as QuadrotorBaseNP._dt_inv_inertia_f */
    double dw_du[12];   /* (3, 4): dt * inv_inertia * mix */
    const long *dims;   /* (layers + 1,): d_0 = n + m, ..., d_L = n */
    const double *const *w;  /* per layer (d_i, d_{i+1}) */
    const double *const *b;  /* per layer (d_{i+1},) */
    const double *slopes;    /* (layers - 1,) PReLU slopes */
    const double *bound;     /* (n,) */
} Model;

typedef struct {
    long horizon, k;         /* T, residual size */
    const long *res_idx;     /* (k,) */
    const double *target;    /* (k,) */
    double eps;              /* smoothing of the norms */
    long nlin;               /* linear constraint rows */
    const long *cons_t, *cons_idx;
    const double *cons_sign, *cons_bound;
    long att;                /* 1: the attitude row ||q_v,T|| <= att_r */
    double att_r;
    long qv[3];
} Task;

/* QuadrotorBaseNP: the step (same operations and order as _step_floats) and, when A != NULL, its Jacobians
 * A (13, 13) and B (13, 4) (as _step_jac). */
static void quad_step(const Model *M, const double *x, const double *u, double *y, double *A, double *B) {
    const double dt = M->dt, h = 0.5 * M->dt;
    double qw = x[6], qx = x[7], qy = x[8], qz = x[9];
    const double wx = x[10], wy = x[11], wz = x[12];
    const double f1 = u[0], f2 = u[1], f3 = u[2], f4 = u[3];
    const double nq = sqrt(qw * qw + qx * qx + qy * qy + qz * qz);
    qw = qw / nq; qx = qx / nq; qy = qy / nq; qz = qz / nq;
    const double a = (f1 + f2 + f3 + f4) * dt / M->mass;
    const double rw = qw + h * (-qx * wx - qy * wy - qz * wz);
    const double rx = qx + h * (qw * wx + qy * wz - qz * wy);
    const double ry = qy + h * (qw * wy - qx * wz + qz * wx);
    const double rz = qz + h * (qw * wz + qx * wy - qy * wx);
    const double nr = sqrt(rw * rw + rx * rx + ry * ry + rz * rz);
    const double *I = M->inertia, *J = M->jinv;
    const double t1 = f4 - f2, t2 = f3 - f1, t3 = (f1 + f3) - (f2 + f4);
    y[0] = x[0] + dt * x[3];
    y[1] = x[1] + dt * x[4];
    y[2] = x[2] + dt * x[5];
    y[3] = x[3] + a * 2.0 * (qx * qz + qw * qy);
    y[4] = x[4] + a * 2.0 * (qy * qz - qw * qx);
    y[5] = x[5] + a * (1.0 - 2.0 * (qx * qx + qy * qy)) - dt * M->g;
    y[6] = rw / nr; y[7] = rx / nr; y[8] = ry / nr; y[9] = rz / nr;
    y[10] = wx + J[0] * (t1 - (wy * I[2] * wz - wz * I[1] * wy));
    y[11] = wy + J[1] * (t2 - (wz * I[0] * wx - wx * I[2] * wz));
    y[12] = wz + J[2] * (t3 - (wx * I[1] * wy - wy * I[0] * wx));
    if (!A) return;
    const double qn[4] = {qw, qx, qy, qz}, qp[4] = {rw / nr, rx / nr, ry / nr, rz / nr};
    memset(A, 0, 13 * 13 * sizeof(double));
    memset(B, 0, 13 * 4 * sizeof(double));
    for (int i = 0; i < 13; i++) A[i * 13 + i] = 1.0;
    for (int i = 0; i < 3; i++) A[i * 13 + 3 + i] = dt;
    const double thrust = (f1 + f2 + f3 + f4) * (dt / M->mass);
    /* d col / d qn with col = R(qn) e_z */
    const double dcol[3][4] = {{2 * qy, 2 * qz, 2 * qw, 2 * qx}, {-2 * qx, -2 * qw, 2 * qz, 2 * qy},
                               {0.0, -4 * qx, -4 * qy, 0.0}};
    const double col[3] = {2.0 * (qx * qz + qw * qy), 2.0 * (qy * qz - qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy)};
    double nQ[4][4], nR[4][4];
    for (int i = 0; i < 4; i++)
        for (int j = 0; j < 4; j++) {
            nQ[i][j] = ((i == j) - qn[i] * qn[j]) / nq;
            nR[i][j] = ((i == j) - qp[i] * qp[j]) / nr;
        }
    for (int i = 0; i < 3; i++) {
        for (int j = 0; j < 4; j++) {
            double s = 0.0;
            for (int k = 0; k < 4; k++) s += dcol[i][k] * nQ[k][j];
            A[(3 + i) * 13 + 6 + j] = thrust * s;
            B[(3 + i) * 4 + j] = (dt / M->mass) * col[i];
        }
    }
    /* qr = qn + h qn (x) [0, w] = (I + h Omega(w)) qn = qn + h Xi(qn) w */
    const double om[4][4] = {{0.0, -wx, -wy, -wz}, {wx, 0.0, wz, -wy}, {wy, -wz, 0.0, wx}, {wz, wy, -wx, 0.0}};
    const double xi[4][3] = {{-qx, -qy, -qz}, {qw, -qz, qy}, {qz, qw, -qx}, {-qy, qx, qw}};
    double P[4][4];
    for (int i = 0; i < 4; i++)
        for (int j = 0; j < 4; j++) {
            double s = 0.0;
            for (int k = 0; k < 4; k++) s += ((i == k) + h * om[i][k]) * nQ[k][j];
            P[i][j] = s;
        }
    for (int i = 0; i < 4; i++) {
        for (int j = 0; j < 4; j++) {
            double s = 0.0;
            for (int k = 0; k < 4; k++) s += nR[i][k] * P[k][j];
            A[(6 + i) * 13 + 6 + j] = s;
        }
        for (int j = 0; j < 3; j++) {
            double s = 0.0;
            for (int k = 0; k < 4; k++) s += nR[i][k] * xi[k][j];
            A[(6 + i) * 13 + 10 + j] = h * s;
        }
    }
    /* w' = w + dt I^-1 (mix f - w x I w);  d(w x Iw)/dw = [w]x diag(I) - [Iw]x */
    const double w3[3] = {wx, wy, wz}, iw[3] = {wx * I[0], wy * I[1], wz * I[2]};
    const double sw[3][3] = {{0.0, -w3[2], w3[1]}, {w3[2], 0.0, -w3[0]}, {-w3[1], w3[0], 0.0}};
    const double si[3][3] = {{0.0, -iw[2], iw[1]}, {iw[2], 0.0, -iw[0]}, {-iw[1], iw[0], 0.0}};
    for (int i = 0; i < 3; i++) {
        for (int j = 0; j < 3; j++) A[(10 + i) * 13 + 10 + j] -= J[i] * (sw[i][j] * I[j] - si[i][j]);
        for (int j = 0; j < 4; j++) B[(10 + i) * 4 + j] = M->dw_du[i * 4 + j];
    }
}

/* phi(x, u) into phi (n,); with jz != NULL also d phi / d [x, u] (n, n + m) by reverse mode from the outputs
 * (the PReLU derivative at a kink from the h >= 0 side, as NumpyMLP). */
static void net(const Model *M, const double *x, const double *u, double *phi, double *jz) {
    const long L = M->layers, n = M->n, m = M->m, nz = n + m;
    double z[MAXZ], h[MAXW], hn[MAXW], mask[MAXL][MAXW];
    memcpy(z, x, n * sizeof(double));
    memcpy(z + n, u, m * sizeof(double));
    long d_in = M->dims[0], d_out = M->dims[1];
    const double *W = M->w[0], *bias = M->b[0];
    for (long j = 0; j < d_out; j++) h[j] = 0.0;
    for (long i = 0; i < d_in; i++) {
        const double zi = z[i], *row = W + i * d_out;
        for (long j = 0; j < d_out; j++) h[j] += zi * row[j];
    }
    for (long j = 0; j < d_out; j++) h[j] += bias[j];
    for (long l = 1; l < L; l++) {
        const double a = M->slopes[l - 1];
        d_in = M->dims[l];
        d_out = M->dims[l + 1];
        W = M->w[l];
        bias = M->b[l];
        for (long j = 0; j < d_in; j++) {
            const int on = h[j] >= 0.0;
            mask[l - 1][j] = on ? 1.0 : a;
            h[j] = on ? h[j] : a * h[j];
        }
        for (long j = 0; j < d_out; j++) hn[j] = 0.0;
        for (long i = 0; i < d_in; i++) {
            const double hi = h[i], *row = W + i * d_out;
            for (long j = 0; j < d_out; j++) hn[j] += hi * row[j];
        }
        for (long j = 0; j < d_out; j++) h[j] = hn[j] + bias[j];
    }
    memcpy(phi, h, n * sizeof(double));
    if (!jz) return;
    /* g (n, d_l): d phi / d (layer l's input), from the last layer down */
    static __thread double g[MAXZ * MAXW], gn[MAXZ * MAXW];
    long d = M->dims[L - 1];
    const double *WL = M->w[L - 1];
    for (long o = 0; o < n; o++)
        for (long j = 0; j < d; j++) g[o * d + j] = WL[j * n + o];
    for (long l = L - 1; l >= 1; l--) {
        const long dp = M->dims[l - 1];  /* layer l - 1's input width */
        const double *Wl = M->w[l - 1];  /* (dp, d) */
        for (long o = 0; o < n; o++) {
            double *go = g + o * d;
            for (long j = 0; j < d; j++) go[j] *= mask[l - 1][j];
            double *out = gn + o * dp;
            for (long i = 0; i < dp; i++) {
                const double *row = Wl + i * d;
                double s = 0.0;
                for (long j = 0; j < d; j++) s += go[j] * row[j];
                out[i] = s;
            }
        }
        d = dp;
        memcpy(g, gn, n * d * sizeof(double));
    }
    memcpy(jz, g, n * nz * sizeof(double));
}

/* y = model(x, u); with A != NULL also A (n, n), B (n, m). */
static void model_step(const Model *M, const double *x, const double *u, double *y, double *A, double *B) {
    const long n = M->n, m = M->m, nz = n + m;
    if (M->base) {
        quad_step(M, x, u, y, A, B);
    } else {
        memset(y, 0, n * sizeof(double));
        if (A) {
            memset(A, 0, n * n * sizeof(double));
            memset(B, 0, n * m * sizeof(double));
        }
    }
    if (!M->layers) return;
    double phi[MAXZ];
    static __thread double jz[MAXZ * MAXZ];
    net(M, x, u, phi, A ? jz : NULL);
    for (long i = 0; i < n; i++) {
        double p = phi[i];
        int keep = 1;
        if (M->has_bound) {
            const double bd = M->bound[i];
            keep = fabs(p) < bd;
            p = p < -bd ? -bd : p;  /* np.minimum(np.maximum(phi, -bound), bound) */
            p = p > bd ? bd : p;
        }
        y[i] += p;
        if (A && keep) {
            for (long j = 0; j < n; j++) A[i * n + j] += jz[i * nz + j];
            for (long j = 0; j < m; j++) B[i * m + j] += jz[i * nz + n + j];
        }
    }
}

/* xs (T + 1, n) from x0 (n,) under U (T, m) */
void sqp_rollout(const Model *M, const double *x0, const double *U, long T, double *xs) {
    const long n = M->n, m = M->m;
    memcpy(xs, x0, n * sizeof(double));
    for (long t = 0; t < T; t++) model_step(M, xs + t * n, U + t * m, xs + (t + 1) * n, NULL, NULL);
}

/* The SQP's merit of a trajectory xs (T + 1, n): sum_t sqrt(||x_t[res] - target||^2 + eps^2) + penalty * sum of
 * the positive constraint values c (nlin + att,), which are written to c; +inf when not finite. */
double sqp_merit(const Task *K, const double *xs, long n, double penalty, double *c) {
    const long T = K->horizon;
    double merit = 0.0;
    for (long t = 1; t <= T; t++) {
        double ss = 0.0;
        for (long j = 0; j < K->k; j++) {
            const double r = xs[t * n + K->res_idx[j]] - K->target[j];
            ss += r * r;
        }
        merit += sqrt(ss + K->eps * K->eps);
    }
    double viol = 0.0;
    for (long i = 0; i < K->nlin; i++) {
        c[i] = K->cons_sign[i] * xs[K->cons_t[i] * n + K->cons_idx[i]] - K->cons_bound[i];
        if (!(c[i] <= 0.0)) viol += c[i];  /* a NaN makes the merit NaN (then +inf), as np.maximum does */
    }
    if (K->att) {
        const double *q = xs + T * n;
        const double a = q[K->qv[0]], b = q[K->qv[1]], d = q[K->qv[2]];
        const double c_att = sqrt(a * a + b * b + d * d + 1e-12) - K->att_r;
        c[K->nlin] = c_att;
        if (!(c_att <= 0.0)) viol += c_att;
    }
    if (K->nlin + K->att) merit += penalty * viol;
    if (!isfinite(merit)) merit = INFINITY;
    return merit;
}

/* The QP's data at the plan (xs (T + 1, n), U (T, m)): the sensitivities S (T + 1, n, T m) (work), the smoothed
 * cost's gradient grad (T m,) and generalised Gauss-Newton Hessian hess (T m, T m) (radial curvature weight
 * `radial`), the linearised constraint rows gcon (nlin + att, T m) and each row's reach sum_j |gcon_ij| urange_j
 * (reach). Returns the curvature scale max(trace(hess) / (T m), 1e-6). */
double sqp_linearize(const Model *M, const Task *K, const double *xs, const double *U, const double *urange,
                     double radial, double *S, double *hess, double *grad, double *gcon, double *reach) {
    const long n = M->n, m = M->m, T = K->horizon, nu = T * m, k = K->k;
    double A[MAXZ * MAXZ], B[MAXZ * MAXZ], y[MAXZ];
    memset(S, 0, (T + 1) * n * nu * sizeof(double));
    for (long t = 0; t < T; t++) {
        model_step(M, xs + t * n, U + t * m, y, A, B);
        const double *St = S + t * n * nu;
        double *Sn = S + (t + 1) * n * nu;
        const long cols = t * m;
        for (long i = 0; i < n; i++) {
            double *out = Sn + i * nu;
            for (long kk = 0; kk < n; kk++) {
                const double aik = A[i * n + kk];
                if (aik == 0.0) continue;
                const double *src = St + kk * nu;
                for (long c = 0; c < cols; c++) out[c] += aik * src[c];
            }
            for (long j = 0; j < m; j++) out[cols + j] = B[i * m + j];
        }
    }
    memset(hess, 0, nu * nu * sizeof(double));
    memset(grad, 0, nu * sizeof(double));
    double v[MAXW], r[MAXZ];
    for (long t = 1; t <= T; t++) {
        const double *St = S + t * n * nu;
        const long cols = t * m;
        double ss = 0.0;
        for (long j = 0; j < k; j++) {
            r[j] = xs[t * n + K->res_idx[j]] - K->target[j];
            ss += r[j] * r[j];
        }
        const double f = sqrt(ss + K->eps * K->eps), inv_f = 1.0 / f, w3 = radial / (f * f * f);
        for (long c = 0; c < cols; c++) {
            double s = 0.0;
            for (long j = 0; j < k; j++) s += r[j] * St[K->res_idx[j] * nu + c];
            v[c] = s;
            grad[c] += s / f;
        }
        for (long j = 0; j < k; j++) {
            const double *row = St + K->res_idx[j] * nu;
            for (long a = 0; a < cols; a++) {
                const double ra = row[a] * inv_f;
                double *ha = hess + a * nu;
                for (long b = 0; b < cols; b++) ha[b] += ra * row[b];
            }
        }
        for (long a = 0; a < cols; a++) {
            const double va = v[a] * w3;
            double *ha = hess + a * nu;
            for (long b = 0; b < cols; b++) ha[b] -= va * v[b];
        }
    }
    double tr = 0.0;
    for (long a = 0; a < nu; a++) tr += hess[a * nu + a];
    for (long i = 0; i < K->nlin; i++) {
        const double *row = S + K->cons_t[i] * n * nu + K->cons_idx[i] * nu;
        const double sg = K->cons_sign[i];
        double *out = gcon + i * nu;
        double rc = 0.0;
        for (long c = 0; c < nu; c++) {
            out[c] = sg * row[c];
            rc += fabs(out[c]) * urange[c];
        }
        reach[i] = rc;
    }
    if (K->att) {
        const double *q = xs + T * n;
        const double a = q[K->qv[0]], b = q[K->qv[1]], d = q[K->qv[2]];
        const double norm = sqrt(a * a + b * b + d * d + 1e-12);
        const double dq[3] = {a / norm, b / norm, d / norm};
        double *out = gcon + K->nlin * nu;
        double rc = 0.0;
        for (long c = 0; c < nu; c++) {
            double s = 0.0;
            for (long j = 0; j < 3; j++) s += dq[j] * S[T * n * nu + K->qv[j] * nu + c];
            out[c] = s;
            rc += fabs(s) * urange[c];
        }
        reach[K->nlin] = rc;
    }
    const double scale = tr / (double)nu;
    return scale > 1e-6 ? scale : 1e-6;
}

/* Backtracking along d (T m,) from U (T, m): for the step lengths alphas (na,) in order, the trial controls
 * Uout[i] = U + alpha_i d, their states xsout[i] (T + 1, n), merits[i] and constraint values cout[i]; stops at the
 * first with merit_i <= merit - 1e-4 alpha_i pred (Armijo) and returns its index, or -1 when none is accepted
 * (then every step length was tried). */
long sqp_line_search(const Model *M, const Task *K, const double *x0, const double *U, const double *d,
                     const double *alphas, long na, double merit, double pred, double penalty, double *Uout,
                     double *xsout, double *merits, double *cout) {
    const long n = M->n, T = K->horizon, nu = T * M->m, nc = K->nlin + K->att;
    for (long i = 0; i < na; i++) {
        const double alpha = alphas[i];
        double *Ui = Uout + i * nu, *xi = xsout + i * (T + 1) * n;
        for (long c = 0; c < nu; c++) Ui[c] = U[c] + alpha * d[c];
        sqp_rollout(M, x0, Ui, T, xi);
        merits[i] = sqp_merit(K, xi, n, penalty, cout + i * (nc > 0 ? nc : 1));
        if (merits[i] <= merit - 1e-4 * alpha * pred) return i;
    }
    return -1;
}

/* model_step for a batch (tests): Y (B, n), and when A != NULL, A (B, n, n), Bm (B, n, m). */
void sqp_step_batch(const Model *M, const double *X, const double *U, long batch, double *Y, double *A,
                    double *Bm) {
    const long n = M->n, m = M->m;
    for (long i = 0; i < batch; i++)
        model_step(M, X + i * n, U + i * m, Y + i * n, A ? A + i * n * n : NULL, A ? Bm + i * n * m : NULL);
}
