//! Baselines for the latency study: a paced two-process ping-pong, one round trip per
//! tick on an absolute grid, over
//! - `atomic`: one cache line of shared memory with atomics, busy-waiting (the hardware
//!   floor);
//! - `iceoryx2`: bare publish/subscribe of a sample the size of the state sample, with
//!   the same wait strategy as the loop;
//! - `uds`: a Unix domain socket, what a user would build without shared memory.
//!
//! The `ping` side paces, measures round trips and writes a `.hgrm` and a JSON summary.

use std::io::{Read, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};

use anyhow::{Context, bail};
use clap::{Args, ValueEnum};
use hdrhistogram::Histogram;
use rotorloop_common::clock::{now_ns, sleep_until_ns};
use rotorloop_common::graph::Topic;
use rotorloop_common::hgrm::write_percentile_distribution;
use rotorloop_common::ipc::domain::Domain;
use rotorloop_common::ipc::wait::Wait;
use rotorloop_common::role::args::{duration_s, rate_hz};
use rotorloop_common::rt::RtSetup;
use rotorloop_common::signals::shutdown_requested;
use rotorloop_common::wire::StateSample;
use rotorloop_monitor::latency::HopStats;
use serde::Serialize;

/// Transport of a baseline.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Kind {
    /// Shared-memory atomics, spin.
    Atomic,
    /// Bare iceoryx2 publish/subscribe (+ event).
    Iceoryx2,
    /// Unix domain stream socket.
    Uds,
}

/// Which end.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Side {
    /// Paces and measures.
    Ping,
    /// Echoes.
    Pong,
}

/// Arguments of one side.
#[derive(Debug, Clone, Args)]
pub struct PingPongArgs {
    /// What carries the exchange.
    #[arg(long, value_enum)]
    pub kind: Kind,
    /// Which end of the exchange this process is.
    #[arg(long, value_enum)]
    pub side: Side,
    /// Rendezvous name (domain / file stem).
    #[arg(long)]
    pub name: String,
    /// Exchanges per second, on an absolute grid, 1 to 100000 Hz.
    #[arg(long, allow_hyphen_values = true, default_value_t = 1000.0, value_parser = rate_hz())]
    pub rate: f64,
    /// How long to exchange, 0.001 to 86400 s.
    #[arg(long, allow_hyphen_values = true, default_value_t = 3.0, value_parser = duration_s())]
    pub seconds: f64,
    /// How each side waits for the other (as the loop's `--wait`).
    #[arg(long, default_value = "event")]
    pub wait: Wait,
    /// The core to pin this side to, 0 to 4095.
    #[arg(long, allow_hyphen_values = true, value_parser = rotorloop_common::role::args::core())]
    pub core: Option<usize>,
    /// Ping: output stem (`STEM.hgrm`, `STEM.json`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// iceoryx2 only: the "host" of this side (`--host` of a run), when the two sides are
    /// joined by link gateways (`rotorloop bench --placement cross-host`).
    #[arg(long)]
    pub host: Option<String>,
}

/// What the ping side reports.
#[derive(Debug, Clone, Serialize)]
pub struct PingPongSummary {
    /// Transport.
    pub kind: Kind,
    /// Round trips requested.
    pub ticks: u64,
    /// Round trips not completed before the next tick.
    pub misses: u64,
    /// Echoes of an earlier ping taken and skipped (across hosts: the handshake's).
    pub stale_echoes: u64,
    /// Round trips whose echo never came (a second without it; across hosts only).
    pub lost: u64,
    /// Achieved tick rate (Hz).
    pub achieved_rate_hz: f64,
    /// Round-trip statistics (ns).
    pub rtt: HopStats,
}

const PAYLOAD: usize = size_of::<StateSample>();

/// How long the ping side waits for a late echo before it counts the round trip lost.
const LOST_AFTER_NS: u64 = 1_000_000_000;

/// Runs one side to the end.
pub fn run(a: &PingPongArgs) -> anyhow::Result<()> {
    for w in (RtSetup { core: a.core, ..RtSetup::default() }).apply(&format!("{:?}", a.side)) {
        eprintln!("warning: {w}");
    }
    let ticks = (a.seconds * a.rate).round().max(1.0) as u64;
    let mut link: Box<dyn Link> = match a.kind {
        Kind::Atomic => Box::new(AtomicLink::open(&a.name, a.side)?),
        Kind::Iceoryx2 => Box::new(IoxLink::open(&a.name, a.host.as_deref(), a.side, a.wait)?),
        Kind::Uds => Box::new(UdsLink::open(&a.name, a.side, a.wait)?),
    };
    match a.side {
        Side::Pong => {
            // Across hosts the last ping can be lost: give up a minute after the run's end.
            let until = now_ns() + ((a.seconds + 60.0) * 1e9) as u64;
            while let Some(seq) = link.recv(until)? {
                link.send(seq)?;
                if seq >= ticks {
                    break;
                }
            }
            Ok(())
        }
        Side::Ping => {
            let mut h = Histogram::<u64>::new_with_bounds(1, 60_000_000_000, 3)?;
            if a.host.is_some() {
                handshake(link.as_mut())?;
            }
            let period = 1e9 / a.rate;
            let start = now_ns() + 50_000_000;
            let (mut misses, mut stale, mut lost) = (0u64, 0u64, 0u64);
            let mut last_wake = start;
            for k in 1..=ticks {
                let deadline = start + (k as f64 * period).round() as u64;
                sleep_until_ns(deadline, 0);
                last_wake = now_ns();
                let t0 = now_ns();
                link.send(k)?;
                let next = start + ((k + 1) as f64 * period).round() as u64;
                // Wait for this round trip; a late echo is a miss and is still awaited,
                // so the pair stays in step.
                // Echoes of an earlier ping (the handshake's) are skipped and counted.
                let mut fresh = |deadline| -> anyhow::Result<Option<u64>> {
                    loop {
                        match link.recv(deadline)? {
                            Some(seq) if seq < k => stale += 1,
                            got => return Ok(got),
                        }
                    }
                };
                let mut got = fresh(next)?;
                if got.is_none() {
                    misses += 1;
                    // Across hosts a sample can be lost: after a second, go on without it.
                    got = fresh(now_ns() + LOST_AFTER_NS)?;
                }
                match got {
                    Some(seq) if seq == k => h.saturating_record(now_ns() - t0),
                    Some(seq) => bail!("echo {seq} for ping {k}"),
                    None if shutdown_requested() => break,
                    None => lost += 1,
                }
            }
            let out = a.out.as_ref().context("--out is required for the ping side")?;
            let mut f = std::fs::File::create(out.with_extension("hgrm"))?;
            write_percentile_distribution(&h, &mut f)?;
            let summary = PingPongSummary {
                kind: a.kind,
                ticks,
                misses,
                stale_echoes: stale,
                lost,
                achieved_rate_hz: (ticks - 1) as f64
                    / ((last_wake - start - period as u64) as f64 / 1e9),
                rtt: HopStats::of(&h),
            };
            rotorloop_common::output::write_json(&out.with_extension("json"), &summary)
        }
    }
}

/// Across hosts: sends sequence 0 every 10 ms until its echo comes back (at most 30 s).
/// Over link gateways a sample sent before the far side's mirror exists is gone, and the
/// first measured ping must not be that one.
fn handshake(link: &mut dyn Link) -> anyhow::Result<()> {
    let until = now_ns() + 30_000_000_000;
    while now_ns() < until && !shutdown_requested() {
        link.send(0)?;
        if link.recv(now_ns() + 10_000_000)? == Some(0) {
            return Ok(());
        }
    }
    bail!("the pong side did not answer within 30 s")
}

trait Link {
    fn send(&mut self, seq: u64) -> anyhow::Result<()>;
    /// The next sequence number, or None at the monotonic deadline / on a signal.
    fn recv(&mut self, deadline_ns: u64) -> anyhow::Result<Option<u64>>;
}

/// Two atomics on separate cache lines of a shared-memory file.
struct AtomicLink {
    map: *mut u8,
    side: Side,
    path: PathBuf,
}

impl AtomicLink {
    fn open(name: &str, side: Side) -> anyhow::Result<Self> {
        let path = PathBuf::from(format!("/dev/shm/rlbench_{name}"));
        let f = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)?;
        f.set_len(4096)?;
        let Ok(map) = rotorloop_common::private::map_shared(&f, 4096, 0) else {
            bail!("cannot map {}", path.display());
        };
        Ok(Self { map, side, path })
    }
    fn cell(&self, which: usize) -> &AtomicU64 {
        // SAFETY: offsets 0 and 128 lie within the 4 KiB mapping and are 8-byte aligned;
        // the mapping lives as long as self.
        unsafe { &*(self.map.add(which * 128) as *const AtomicU64) }
    }
    fn lines(&self) -> (usize, usize) {
        match self.side {
            Side::Ping => (0, 1),
            Side::Pong => (1, 0),
        }
    }
}

impl Drop for AtomicLink {
    fn drop(&mut self) {
        // SAFETY: unmaps what open() mapped.
        unsafe { libc::munmap(self.map.cast(), 4096) };
        if self.side == Side::Ping {
            let _ = std::fs::remove_file(&self.path);
        }
    }
}

impl Link for AtomicLink {
    fn send(&mut self, seq: u64) -> anyhow::Result<()> {
        self.cell(self.lines().0).store(seq, Ordering::Release);
        Ok(())
    }
    fn recv(&mut self, deadline_ns: u64) -> anyhow::Result<Option<u64>> {
        let cell = self.cell(self.lines().1);
        let seen = self.cell(self.lines().0).load(Ordering::Relaxed);
        let mut n = 0u32;
        loop {
            let v = cell.load(Ordering::Acquire);
            // ping waits for the echo of what it sent; pong for anything new
            let ready = match self.side {
                Side::Ping => v == seen && v != 0,
                Side::Pong => v > seen,
            };
            if ready {
                return Ok(Some(v));
            }
            n = n.wrapping_add(1);
            if n % 1024 == 0 && (now_ns() >= deadline_ns || shutdown_requested()) {
                return Ok(None);
            }
            std::hint::spin_loop();
        }
    }
}

/// Bare iceoryx2: ping and pong services of a state-sized payload.
struct IoxLink {
    _node: iceoryx2::node::Node<iceoryx2::prelude::ipc::Service>,
    out: rotorloop_common::ipc::ports::Outbox<StateSample>,
    inbox: rotorloop_common::ipc::ports::Inbox<StateSample>,
    wait: Wait,
}

impl IoxLink {
    fn open(name: &str, host: Option<&str>, side: Side, wait: Wait) -> anyhow::Result<Self> {
        let domain = Domain::on_host(name, host)?;
        let node = domain.node(&format!("{side:?}"))?;
        // ping publishes on `state` and listens on `torque`; pong the other way round.
        let (tx, rx) = match side {
            Side::Ping => (Topic::State, Topic::Torque),
            Side::Pong => (Topic::Torque, Topic::State),
        };
        let out = domain.outbox::<StateSample>(&node, tx)?;
        let inbox = domain.inbox::<StateSample>(&node, rx, 4, wait.listens())?;
        // Both ends must be connected before the first ping.
        let until = now_ns() + 10_000_000_000;
        while out.subscribers() < 1 {
            if now_ns() > until || shutdown_requested() {
                bail!("iceoryx2 baseline: peer did not connect");
            }
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        out.update_connections();
        Ok(Self { _node: node, out, inbox, wait })
    }
}

impl Link for IoxLink {
    fn send(&mut self, seq: u64) -> anyhow::Result<()> {
        let mut s = StateSample::of(
            seq,
            0.0,
            &rotorloop_common::params::RotorBodyState {
                r: glam::DMat3::IDENTITY,
                omega: glam::DVec3::ZERO,
                omega_r: glam::DVec3::ZERO,
                theta: glam::DVec3::ZERO,
            },
        );
        s.tick = seq;
        self.out.send(s, |s| s.publish_ns = now_ns())?;
        Ok(())
    }
    fn recv(&mut self, deadline_ns: u64) -> anyhow::Result<Option<u64>> {
        Ok(self.inbox.wait_for(self.wait, deadline_ns, |i| Ok(i.take()?.map(|s| s.tick)))?)
    }
}

/// A Unix stream socket; messages are state-sized.
struct UdsLink {
    stream: UnixStream,
    wait: Wait,
    buf: [u8; PAYLOAD],
    path: Option<PathBuf>,
}

impl UdsLink {
    fn open(name: &str, side: Side, wait: Wait) -> anyhow::Result<Self> {
        let path = std::env::temp_dir().join(format!("rlbench_{name}.sock"));
        let (stream, own) = match side {
            Side::Pong => {
                let _ = std::fs::remove_file(&path);
                let l = UnixListener::bind(&path)
                    .with_context(|| format!("bind {}", path.display()))?;
                (l.accept()?.0, Some(path))
            }
            Side::Ping => {
                let until = now_ns() + 10_000_000_000;
                loop {
                    match UnixStream::connect(&path) {
                        Ok(s) => break (s, None),
                        Err(_) if now_ns() < until && !shutdown_requested() => {
                            std::thread::sleep(std::time::Duration::from_millis(2))
                        }
                        Err(e) => return Err(e).context("uds baseline: connect"),
                    }
                }
            }
        };
        stream.set_nonblocking(matches!(wait, Wait::Spin))?;
        Ok(Self { stream, wait, buf: [0; PAYLOAD], path: own })
    }
}

impl Drop for UdsLink {
    fn drop(&mut self) {
        if let Some(p) = &self.path {
            let _ = std::fs::remove_file(p);
        }
    }
}

impl Link for UdsLink {
    fn send(&mut self, seq: u64) -> anyhow::Result<()> {
        self.buf[..8].copy_from_slice(&seq.to_le_bytes());
        let nb = matches!(self.wait, Wait::Spin);
        self.stream.set_nonblocking(false)?;
        self.stream.write_all(&self.buf)?;
        self.stream.set_nonblocking(nb)?;
        Ok(())
    }
    fn recv(&mut self, deadline_ns: u64) -> anyhow::Result<Option<u64>> {
        let mut got = 0;
        let start = now_ns();
        while got < PAYLOAD {
            let now = now_ns();
            if (now >= deadline_ns || shutdown_requested()) && got == 0 {
                return Ok(None);
            }
            let blocking = match self.wait {
                Wait::Spin => false,
                Wait::Event | Wait::Poll { .. } => true,
                Wait::Hybrid { spin_ns } => now - start >= spin_ns,
            };
            if blocking {
                let left = deadline_ns.saturating_sub(now).clamp(1_000, 10_000_000);
                self.stream.set_nonblocking(false)?;
                self.stream.set_read_timeout(Some(std::time::Duration::from_nanos(left)))?;
            } else {
                self.stream.set_nonblocking(true)?;
            }
            match self.stream.read(&mut self.buf[got..]) {
                Ok(0) => return Ok(None),
                Ok(n) => got += n,
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) =>
                {
                    std::hint::spin_loop()
                }
                Err(e) => return Err(e.into()),
            }
        }
        let mut b = [0u8; 8];
        b.copy_from_slice(&self.buf[..8]);
        Ok(Some(u64::from_le_bytes(b)))
    }
}

/// Arguments of the CPU hog.
#[derive(Debug, Clone, Args)]
pub struct HogArgs {
    /// The core to keep busy.
    #[arg(long, allow_negative_numbers = true)]
    pub core: Option<usize>,
}

/// Spins until a termination signal.
pub fn hog(a: &HogArgs) -> anyhow::Result<()> {
    let _ = (RtSetup { core: a.core, ..RtSetup::default() }).apply("hog");
    let mut x = 0u64;
    while !shutdown_requested() {
        for _ in 0..100_000 {
            x = std::hint::black_box(x.wrapping_mul(6364136223846793005).wrapping_add(1));
        }
    }
    Ok(())
}
