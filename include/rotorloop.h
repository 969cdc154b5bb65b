/* rotorloop's C API: take the controller's place in a rotorloop run from C, C++ or
 * generated C (docs/wire.md, "A controller in C").
 *
 * Library: librotorloop_c.so, built by `cargo build --release --workspace` into
 * target/release/ (capi/src/lib.rs). Link with -lrotorloop_c; the samples' layouts are
 * rotorloop_wire.h (generated from the Rust types).
 *
 * One handle per process, opened once: it opens the run's controller node and its
 * services with the QoS of docs/wire.md. After the open the library allocates nothing
 * per tick (a publish allocates only what iceoryx2's own loan and send of a sample do,
 * as the built-in controller's publish), no call starts a thread, and the library keeps
 * no thread: each call runs on the caller's thread and returns. A call that fails returns a status other than ROTORLOOP_OK and
 * ROTORLOOP_TIMEOUT; rotorloop_last_error() then says why, in words.
 *
 * A tick, as examples/c/controller.c does it:
 *
 *   rotorloop_controller_receive_state(c, 100000000, &state, &recv_ns);  // newest state
 *   rotorloop_controller_reference(c, state.tick, timeout, &ref);        // its reference
 *   rotorloop_controller_loan(c, &torque);                               // in shared memory
 *   torque->tick = state.tick; ... write the answer in place ...
 *   rotorloop_controller_publish(c);                                     // send + wake
 */
#ifndef ROTORLOOP_H
#define ROTORLOOP_H

#include <stdint.h>

#include "rotorloop_wire.h"

#ifdef __cplusplus
extern "C" {
#endif

/* What a call returns. */
typedef enum rotorloop_status {
    ROTORLOOP_OK = 0,
    /* Nothing arrived before the timeout: not an error (look again, or give up). */
    ROTORLOOP_TIMEOUT = 1,
    /* A NULL pointer, a string that is not UTF-8, a bad domain name or wait mode. */
    ROTORLOOP_ERR_ARGUMENT = 2,
    /* A live controller already holds this domain's controller node. */
    ROTORLOOP_ERR_ROLE_TAKEN = 3,
    /* The domain's services carry another layout version (another rotorloop build). */
    ROTORLOOP_ERR_LAYOUT = 4,
    /* iceoryx2 refused (open, loan, send, receive, wait). */
    ROTORLOOP_ERR_IPC = 5,
    /* controller.json cannot be read or parsed, or has another layout version. */
    ROTORLOOP_ERR_CONFIG = 6,
    /* A call out of order: publish without a loan, a second loan before the publish. */
    ROTORLOOP_ERR_ORDER = 7
} rotorloop_status;

/* The layout version of controller.json this library reads. */
#define ROTORLOOP_CONTROLLER_JSON_VERSION UINT64_C(1)

/* The law's parameters, from controller.json ($ROTORLOOP_CONTROLLER_JSON). Matrices
 * row-major; a limit that is not set is 0 with its has_ flag 0. */
typedef struct rotorloop_law_config {
    uint64_t layout_version;      /* controller.json's layout_version */
    char law[32];                 /* "geometric-pid" or "mrp-pid", NUL-terminated */
    uint64_t internal_actuation;  /* 1: answer with the rotor torque u; 0: body torque tau */
    uint64_t ticks;               /* ticks in the run */
    double dt_s;                  /* the tick (s) */
    double rate_hz;               /* the rate (Hz) */
    double kp, kd, ki;            /* the gains */
    double p_row_major[9];        /* P */
    double inertia_row_major[9];  /* the model of I: the body without the rotors' spin inertia (kg m^2) */
    double rotor_inertia[3];      /* the model of K's diagonal: the rotors' spin inertia (kg m^2) */
    uint64_t has_rotor_torque_limit;
    double rotor_torque_limit_nm; /* u_max */
    uint64_t has_rotor_rate_limit;
    double rotor_rate_limit_rad_s; /* Omega_max */
    uint64_t anti_windup_conditional; /* 1: conditional integration; 0: none */
} rotorloop_law_config;

ROTORLOOP_STATIC_ASSERT(sizeof(rotorloop_law_config) == 304, "rotorloop_law_config layout");

/* A controller's port of a run's domain (opaque). */
typedef struct rotorloop_controller rotorloop_controller;

/* The message of the last call that failed on this thread ("" if none), valid until
 * the next failing call on the same thread. */
const char *rotorloop_last_error(void);

/* CLOCK_MONOTONIC in ns: the clock of every stamp on the wire. */
uint64_t rotorloop_now_ns(void);

/* Reads controller.json (path; NULL: $ROTORLOOP_CONTROLLER_JSON) into *out. */
rotorloop_status rotorloop_law_config_load(const char *path, rotorloop_law_config *out);

/* Opens the controller's ports of run domain `domain` (NULL: $ROTORLOOP_DOMAIN), waiting
 * as `wait` says ("event", "spin" or "hybrid"; NULL: $ROTORLOOP_WAIT, else "event").
 * The node is named rotorloop/<domain>/controller; a second live one is refused
 * (ROTORLOOP_ERR_ROLE_TAKEN). Free with rotorloop_controller_close. */
rotorloop_status rotorloop_controller_open(const char *domain, const char *wait,
                                           rotorloop_controller **out);

/* Takes every state waiting; the newest goes to *state (older ones are skipped and
 * counted in the next torque's states_skipped), and when it was taken (ns) to *recv_ns
 * (may be NULL). Waits for one up to timeout_ns (0: only looks): ROTORLOOP_TIMEOUT when
 * none came. */
rotorloop_status rotorloop_controller_receive_state(rotorloop_controller *c, uint64_t timeout_ns,
                                                    StateSample *state, uint64_t *recv_ns);

/* The reference of tick `tick` into *reference, waiting for it up to timeout_ns (0: only
 * looks; the reference works ahead, so it is usually there). ROTORLOOP_TIMEOUT when it
 * did not come: *reference is then the newest reference held for an earlier tick (its
 * tick field says which; ROTORLOOP_NO_TICK when none), for a controller that propagates
 * it. The library keeps the last 64 references by tick; one more than 48 ticks beyond
 * the newest state taken is refused (it would displace a true one). */
rotorloop_status rotorloop_controller_reference(rotorloop_controller *c, uint64_t tick,
                                                uint64_t timeout_ns, ReferenceSample *reference);

/* A torque sample in shared memory, every byte zero, in *sample: write the answer in
 * place, then rotorloop_controller_publish. Valid until that publish. Each publish loans
 * the next sample once its own is on its way (off the path from state to torque, as the
 * built-in controller does), so this call then only zeroes it. */
rotorloop_status rotorloop_controller_loan(rotorloop_controller *c, TorqueSample **sample);

/* Publishes the loaned sample and wakes its readers. Sets just before the send:
 * publish_ns, prev_tick, prev_publish, published, states_received, states_skipped.
 * Every other field is the controller's (tick, torques, flags, state_recv_ns,
 * validated_ns, paired_ns, computed_ns, reference_misses, states_lost, states_rejected,
 * references_rejected). */
rotorloop_status rotorloop_controller_publish(rotorloop_controller *c);

/* Readers of the torque topic now connected: 0 once the plant and the monitor have
 * unsubscribed (after the run's last tick). */
uint64_t rotorloop_controller_readers(const rotorloop_controller *c);

/* Waits until the torque topic has no readers or linger_ns passed (the built-in
 * controller lingers up to 10 s, so its last answers are read), then closes every port.
 * NULL is ignored. */
void rotorloop_controller_close(rotorloop_controller *c, uint64_t linger_ns);

#ifdef __cplusplus
}
#endif

#endif /* ROTORLOOP_H */
