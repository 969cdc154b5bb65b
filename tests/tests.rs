//! Every integration test, in one binary (ripgrep's pattern: `autotests = false` in
//! `Cargo.toml`). One binary links the workspace once instead of once per file, which
//! is most of a cold `cargo test`'s link time and of `target`'s size.
//!
//! Two test binaries stay apart: `no_alloc` installs a counting global allocator, which
//! would count every other test's allocations too, and `readme_commands` runs cargo
//! builds that would starve the loops of the process tests beside it (`Cargo.toml`).
//!
//! Run one file's tests with a filter: `cargo test --test tests faults::`.

mod common;

mod actuators;
mod almost_global;
mod bad_input;
mod bench_smoke;
mod c_controller;
mod cli_outputs;
mod controller_cmd;
mod crash;
mod delay;
mod export;
mod faults;
mod fuzz_inputs;
mod hostile;
mod incidents;
mod layout;
mod live;
mod memory;
mod misbehaving;
mod multiprocess;
mod observe;
mod physics;
mod split;
mod supervision;
mod tracking;
mod wire_contract;
