// A thin C++ layer over rotorloop's C API (rotorloop.h): the handle as a move-only RAII
// object, and every failing call as a rotorloop::error carrying the status and the
// library's message. Nothing here allocates per tick (an error's message is built only
// when a call fails).
#ifndef ROTORLOOP_HPP
#define ROTORLOOP_HPP

#include <stdexcept>
#include <string>

#include "rotorloop.h"

namespace rotorloop {

// A failed call: its status and rotorloop_last_error()'s message.
class error : public std::runtime_error {
public:
    error(rotorloop_status status, const char *call)
        : std::runtime_error(std::string(call) + ": " + rotorloop_last_error()), status_(status) {}
    rotorloop_status status() const noexcept { return status_; }

private:
    rotorloop_status status_;
};

// Throws for anything but ROTORLOOP_OK and ROTORLOOP_TIMEOUT; returns whether it was OK.
inline bool check(rotorloop_status s, const char *call) {
    if (s != ROTORLOOP_OK && s != ROTORLOOP_TIMEOUT) throw error(s, call);
    return s == ROTORLOOP_OK;
}

// controller.json (nullptr: $ROTORLOOP_CONTROLLER_JSON).
inline rotorloop_law_config law_config(const char *path = nullptr) {
    rotorloop_law_config c;
    check(rotorloop_law_config_load(path, &c), "rotorloop_law_config_load");
    return c;
}

// The controller's port of a run's domain; closed (with `linger_ns` for the readers) when
// it goes out of scope.
class controller {
public:
    explicit controller(const char *domain = nullptr, const char *wait = nullptr,
                        uint64_t linger_ns = 10000000000ull)
        : linger_ns_(linger_ns) {
        check(rotorloop_controller_open(domain, wait, &c_), "rotorloop_controller_open");
    }
    ~controller() { rotorloop_controller_close(c_, linger_ns_); }
    controller(const controller &) = delete;
    controller &operator=(const controller &) = delete;
    controller(controller &&o) noexcept : c_(o.c_), linger_ns_(o.linger_ns_) { o.c_ = nullptr; }
    controller &operator=(controller &&) = delete;

    // The newest state; false when none came within timeout_ns.
    bool receive_state(uint64_t timeout_ns, StateSample &state, uint64_t &recv_ns) {
        return check(rotorloop_controller_receive_state(c_, timeout_ns, &state, &recv_ns),
                     "rotorloop_controller_receive_state");
    }
    // Tick's reference; false when it did not come (then `ref` is the newest earlier one).
    bool reference(uint64_t tick, uint64_t timeout_ns, ReferenceSample &ref) {
        return check(rotorloop_controller_reference(c_, tick, timeout_ns, &ref),
                     "rotorloop_controller_reference");
    }
    // A zeroed torque sample in shared memory, valid until publish().
    TorqueSample &loan() {
        TorqueSample *t = nullptr;
        check(rotorloop_controller_loan(c_, &t), "rotorloop_controller_loan");
        return *t;
    }
    void publish() { check(rotorloop_controller_publish(c_), "rotorloop_controller_publish"); }
    uint64_t readers() const { return rotorloop_controller_readers(c_); }

private:
    rotorloop_controller *c_ = nullptr;
    uint64_t linger_ns_;
};

}  // namespace rotorloop

#endif  // ROTORLOOP_HPP
