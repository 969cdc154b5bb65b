/* The paper's geometric PID tracking law as a rotorloop controller in C, written from
 * docs/wire.md, include/rotorloop.h and the spec (dynamics-and-control.md, "The control
 * law") alone.
 *
 *   make -C examples/c
 *   rotorloop run --scenario paper-sinusoid --mode lockstep \
 *       --controller-cmd examples/c/controller --out out/c
 *
 * The law at tick k, with the integral state xi_k:
 *   E = R_d R^T,  s = vee(P E - E^T P),  eta = R (Omega_d - Omega)
 *   a = -kp s - kd eta - ki xi_k
 *   Omega_dot* = Omega_d_dot + Omega x Omega_d - R^T a
 *   tau = I Omega_dot* - (I Omega) x Omega
 *   u = (K (Omega + Omega_r)) x Omega - tau
 *   xi_{k+1} = xi_k + dt s   (after the tick's torques; held under conditional
 *                             anti-windup on a saturated tick unless it shrinks xi)
 *
 * Every product is written in the order docs/wire.md gives ("A controller in C":
 * a matrix times a vector sums its columns left to right), so in lockstep the trace is
 * the built-in law's bit for bit. Built with -ffp-contract=off: a fused multiply-add
 * rounds once where the Rust law rounds twice.
 *
 * A restart continues from ROTORLOOP_STATE_DIR/pid.state (the last answer and xi, two
 * copies and a generation counter in a mapped file, written before each send): a state
 * it answered already gets the same answer again (a skipped one skipped again), never a
 * second integration. The launcher empties that directory at the start of every run,
 * never between restarts.
 */
#define _GNU_SOURCE
#include <fcntl.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <unistd.h>

#include "rotorloop.h"

typedef struct { double x, y, z; } v3;
/* Row-major: m[3*i + j] is row i, column j. */
typedef struct { double m[9]; } m3;

static v3 v(double x, double y, double z) { v3 r = {x, y, z}; return r; }
static v3 add(v3 a, v3 b) { return v(a.x + b.x, a.y + b.y, a.z + b.z); }
static v3 sub(v3 a, v3 b) { return v(a.x - b.x, a.y - b.y, a.z - b.z); }
static v3 scale(double k, v3 a) { return v(a.x * k, a.y * k, a.z * k); }
static v3 hadamard(v3 a, v3 b) { return v(a.x * b.x, a.y * b.y, a.z * b.z); }
static v3 cross(v3 a, v3 b) {
    return v(a.y * b.z - b.y * a.z, a.z * b.x - b.z * a.x, a.x * b.y - b.x * a.y);
}
static v3 load3(const double *p) { return v(p[0], p[1], p[2]); }
static void store3(double *p, v3 a) { p[0] = a.x; p[1] = a.y; p[2] = a.z; }

/* M v = (col0 v.x + col1 v.y) + col2 v.z, each row in that order. */
static v3 mv(const m3 *a, v3 b) {
    const double *m = a->m;
    return v((m[0] * b.x + m[1] * b.y) + m[2] * b.z,
             (m[3] * b.x + m[4] * b.y) + m[5] * b.z,
             (m[6] * b.x + m[7] * b.y) + m[8] * b.z);
}
/* A B, column by column as M v. */
static m3 mm(const m3 *a, const m3 *b) {
    m3 r;
    for (int j = 0; j < 3; j++) {
        v3 c = mv(a, v(b->m[j], b->m[3 + j], b->m[6 + j]));
        r.m[j] = c.x; r.m[3 + j] = c.y; r.m[6 + j] = c.z;
    }
    return r;
}
static m3 transpose(const m3 *a) {
    m3 r;
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) r.m[3 * i + j] = a->m[3 * j + i];
    return r;
}
/* vee of a skew matrix: 0.5 (A32 - A23, A13 - A31, A21 - A12). */
static v3 vee(const m3 *a) {
    const double *m = a->m;
    return v(0.5 * (m[7] - m[5]), 0.5 * (m[2] - m[6]), 0.5 * (m[3] - m[1]));
}

/* Rodrigues, as the spec's exp (for a missing reference propagated in real time). */
static m3 exp_so3(v3 t) {
    double a2 = t.x * t.x + t.y * t.y + t.z * t.z, s, c;
    if (a2 < 1e-8) {
        s = 1.0 - a2 / 6.0 + a2 * a2 / 120.0;
        c = 0.5 - a2 / 24.0 + a2 * a2 / 720.0;
    } else {
        double a = sqrt(a2);
        s = sin(a) / a;
        c = (1.0 - cos(a)) / a2;
    }
    m3 k = {{0.0, -t.z, t.y, t.z, 0.0, -t.x, -t.y, t.x, 0.0}};
    m3 kk = mm(&k, &k), r;
    for (int i = 0; i < 9; i++) r.m[i] = (((i % 4) == 0 ? 1.0 : 0.0) + k.m[i] * s) + kk.m[i] * c;
    return r;
}

static int finite_all(const double *p, int n, double bound) {
    for (int i = 0; i < n; i++)
        if (!isfinite(p[i]) || fabs(p[i]) > bound) return 0;
    return 1;
}

/* R on SO(3) as docs/wire.md's tolerance says: entries within 2, every entry of
 * R^T R - I and |det R - 1| at most 1e-6. */
static int on_so3(const double *r) {
    if (!finite_all(r, 9, 2.0)) return 0;
    m3 a, at, g;
    memcpy(a.m, r, sizeof a.m);
    at = transpose(&a);
    g = mm(&at, &a);
    for (int i = 0; i < 9; i++)
        if (fabs(g.m[i] - ((i % 4) == 0 ? 1.0 : 0.0)) > 1e-6) return 0;
    double det = r[0] * (r[4] * r[8] - r[5] * r[7]) - r[1] * (r[3] * r[8] - r[5] * r[6]) +
                 r[2] * (r[3] * r[7] - r[4] * r[6]);
    return fabs(det - 1.0) <= 1e-6;
}

/* What a restart continues from. */
typedef struct {
    uint64_t tick;
    double xi[3], u[3], tau[3];
    uint64_t flags; /* ROTORLOOP_TORQUE_SKIPPED when it was no torque */
} answer;
typedef struct {
    uint64_t generation;
    answer copy[2];
} resume_file;

static resume_file *open_resume(void) {
    const char *dir = getenv("ROTORLOOP_STATE_DIR");
    if (!dir) return NULL;
    char path[4096];
    snprintf(path, sizeof path, "%s/pid.state", dir);
    int fd = open(path, O_RDWR | O_CREAT, 0600);
    if (fd < 0 || ftruncate(fd, sizeof(resume_file)) != 0) {
        perror(path);
        exit(1);
    }
    void *p = mmap(NULL, sizeof(resume_file), PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
    close(fd);
    if (p == MAP_FAILED) {
        perror("mmap");
        exit(1);
    }
    return p;
}

/* The copy not in use first, then the generation that points at it. */
static void store_resume(resume_file *f, const answer *a) {
    uint64_t next = f->generation + 1;
    f->copy[next % 2] = *a;
    __atomic_store_n(&f->generation, next, __ATOMIC_RELEASE);
}

typedef struct {
    rotorloop_law_config cfg;
    m3 p, inertia;
    v3 k;
} law;

/* One tick of the law with integral state *xi (advanced after the torques). */
static void law_step(const law *l, const StateSample *x, const m3 *rd, v3 wd, v3 wdd, v3 *xi,
                     v3 *u_out, v3 *tau_out) {
    const rotorloop_law_config *c = &l->cfg;
    m3 r, rt, e, et, pe, etp, d;
    memcpy(r.m, x->r_row_major, sizeof r.m);
    v3 omega = load3(x->omega_body_rad_s), omega_r = load3(x->omega_rotor_rad_s);
    rt = transpose(&r);
    e = mm(rd, &rt);
    pe = mm(&l->p, &e);
    et = transpose(&e);
    etp = mm(&et, &l->p);
    for (int i = 0; i < 9; i++) d.m[i] = pe.m[i] - etp.m[i];
    v3 eta = mv(&r, sub(wd, omega));
    v3 s = vee(&d);
    v3 a = sub(sub(scale(-c->kp, s), scale(c->kd, eta)), scale(c->ki, *xi));
    v3 ods = sub(add(wdd, cross(omega, wd)), mv(&rt, a));
    v3 i_omega = mv(&l->inertia, omega);
    v3 tau = sub(mv(&l->inertia, ods), cross(i_omega, omega));
    v3 u = sub(cross(hadamard(l->k, add(omega, omega_r)), omega), tau);
    /* The plant's limits applied to the same state: does this tick saturate? */
    int saturated = 0;
    double uu[3] = {u.x, u.y, u.z}, wr[3] = {omega_r.x, omega_r.y, omega_r.z};
    for (int i = 0; i < 3; i++) {
        double w = uu[i];
        if (c->has_rotor_torque_limit) w = fmin(fmax(w, -c->rotor_torque_limit_nm), c->rotor_torque_limit_nm);
        if (c->has_rotor_rate_limit && fabs(wr[i]) >= c->rotor_rate_limit_rad_s && w * wr[i] > 0.0) w = 0.0;
        saturated |= w != uu[i];
    }
    double s_dot_xi = s.x * xi->x + s.y * xi->y + s.z * xi->z;
    int hold = saturated && c->anti_windup_conditional && s_dot_xi >= 0.0;
    if (!hold) *xi = add(*xi, scale(c->dt_s, s));
    *u_out = u;
    *tau_out = tau;
}

static void check(rotorloop_status s, const char *what) {
    if (s != ROTORLOOP_OK && s != ROTORLOOP_TIMEOUT) {
        fprintf(stderr, "controller.c: %s: %s (status %d)\n", what, rotorloop_last_error(), (int)s);
        exit(1);
    }
}

int main(int argc, char **argv) {
    law l;
    check(rotorloop_law_config_load(NULL, &l.cfg), "reading controller.json");
    if (strcmp(l.cfg.law, "geometric-pid") != 0) {
        fprintf(stderr, "controller.c: only the geometric-pid law (this run's is %s)\n", l.cfg.law);
        return 2;
    }
    memcpy(l.p.m, l.cfg.p_row_major, sizeof l.p.m);
    memcpy(l.inertia.m, l.cfg.inertia_row_major, sizeof l.inertia.m);
    l.k = load3(l.cfg.rotor_inertia);
    /* Real time: how long a missing reference is propagated (the built-in's
     * --reference-hold-ticks, appended by the launcher when given; default 1000). */
    uint64_t hold_ticks = 1000;
    for (int i = 1; i + 1 < argc; i++)
        if (strcmp(argv[i], "--reference-hold-ticks") == 0) hold_ticks = strtoull(argv[i + 1], NULL, 10);
    const char *mode = getenv("ROTORLOOP_MODE");
    int lockstep = mode && strcmp(mode, "lockstep") == 0;

    rotorloop_controller *c = NULL;
    check(rotorloop_controller_open(NULL, NULL, &c), "opening the controller's ports");
    resume_file *resume = open_resume();
    answer last = {ROTORLOOP_NO_TICK, {0, 0, 0}, {0, 0, 0}, {0, 0, 0}, 0};
    if (resume && resume->generation > 0) {
        last = resume->copy[resume->generation % 2];
        fprintf(stderr, "controller.c: resuming after tick %llu with its integral state\n",
                (unsigned long long)last.tick);
    }
    v3 xi = load3(last.xi);
    uint64_t reference_misses = 0, states_rejected = 0, held = 0;
    ReferenceSample held_ref = {0};
    held_ref.tick = ROTORLOOP_NO_TICK;

    for (;;) {
        StateSample x;
        uint64_t recv_ns;
        if (rotorloop_controller_receive_state(c, 100000000, &x, &recv_ns) == ROTORLOOP_TIMEOUT) continue;
        uint64_t k = x.tick;
        TorqueSample *t;
        if (last.tick != ROTORLOOP_NO_TICK && k <= last.tick) {
            if (k < last.tick) continue; /* older than the last answer: nothing to send */
            /* Answered already (a restarted plant asks again): the same answer, a skipped
             * one skipped again (its zeros are no torque to apply). */
            check(rotorloop_controller_loan(c, &t), "loaning");
            t->tick = k;
            store3(t->rotor_torque_nm, load3(last.u));
            store3(t->body_torque_nm, load3(last.tau));
            t->flags = last.flags;
            t->state_recv_ns = t->validated_ns = t->paired_ns = t->computed_ns = recv_ns;
            t->reference_misses = reference_misses;
            t->states_rejected = states_rejected;
            check(rotorloop_controller_publish(c), "publishing");
            continue;
        }
        int ok = on_so3(x.r_row_major) && finite_all(x.omega_body_rad_s, 3, 1e9) &&
                 finite_all(x.omega_rotor_rad_s, 3, 1e9);
        states_rejected += !ok;
        uint64_t validated = rotorloop_now_ns();
        ReferenceSample ref;
        m3 rd;
        int have = 0;
        if (ok) {
            rotorloop_status s = rotorloop_controller_reference(c, k, 0, &ref);
            if (s == ROTORLOOP_TIMEOUT) {
                reference_misses++;
                /* Lockstep: wait for it. Real time: propagate the last one we paired. */
                while (lockstep && s == ROTORLOOP_TIMEOUT)
                    s = rotorloop_controller_reference(c, k, 100000000, &ref);
            }
            check(s, "reading the reference");
            if (s == ROTORLOOP_OK && on_so3(ref.r_d_row_major)) {
                memcpy(rd.m, ref.r_d_row_major, sizeof rd.m);
                held_ref = ref;
                held = 0;
                have = 1;
            } else if (held_ref.tick != ROTORLOOP_NO_TICK && held_ref.tick < k && ++held <= hold_ticks) {
                ref = held_ref;
                m3 r0;
                memcpy(r0.m, held_ref.r_d_row_major, sizeof r0.m);
                m3 step = exp_so3(scale((double)(k - held_ref.tick) * l.cfg.dt_s, load3(ref.omega_d_rad_s)));
                rd = mm(&r0, &step);
                have = 1;
            }
        }
        uint64_t paired = rotorloop_now_ns();
        answer a = {k, {xi.x, xi.y, xi.z}, {0, 0, 0}, {0, 0, 0}, have ? 0 : ROTORLOOP_TORQUE_SKIPPED};
        if (have) {
            v3 u, tau;
            law_step(&l, &x, &rd, load3(ref.omega_d_rad_s), load3(ref.omega_d_dot_rad_s2), &xi, &u, &tau);
            store3(a.xi, xi);
            store3(a.u, u);
            store3(a.tau, tau);
        }
        uint64_t computed = rotorloop_now_ns();
        if (resume) store_resume(resume, &a); /* before the send: a kill between re-sends it */
        last = a;
        check(rotorloop_controller_loan(c, &t), "loaning");
        t->tick = k;
        store3(t->rotor_torque_nm, load3(a.u));
        store3(t->body_torque_nm, load3(a.tau));
        t->flags = a.flags;
        t->state_recv_ns = recv_ns;
        t->validated_ns = validated;
        t->paired_ns = paired;
        t->computed_ns = computed;
        t->reference_misses = reference_misses;
        t->states_rejected = states_rejected;
        check(rotorloop_controller_publish(c), "publishing");
        if (x.flags & ROTORLOOP_FLAG_LAST) break;
    }
    rotorloop_controller_close(c, 10000000000ull);
    return 0;
}
