//! The doctor's items, from a [`Probe`] and the `/proc` and `/sys` files under a root
//! (`/` on a live system; a fixture's copy in tests). Each reads a few small files: the
//! whole report costs a fork and a few hundred reads.

use std::path::{Path, PathBuf};

use super::Item;
use super::probe::Probe;
use crate::cpus::{format_list, parse_list};

/// The files under a root.
struct Sys(PathBuf);

impl Sys {
    fn read(&self, rel: &str) -> Option<String> {
        std::fs::read_to_string(self.0.join(rel)).ok().map(|s| s.trim().to_owned())
    }
    fn list(&self, rel: &str) -> Option<Vec<usize>> {
        self.read(rel)
            .and_then(|s| if s.is_empty() { Some(Vec::new()) } else { parse_list(&s, rel).ok() })
    }
    fn entries(&self, rel: &str) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(self.0.join(rel))
            .into_iter()
            .flatten()
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }
    /// The value of `key=` on the kernel's command line.
    fn cmdline(&self, key: &str) -> Option<String> {
        let line = self.read("proc/cmdline")?;
        let line = line.split(" -- ").next().unwrap_or_default().to_owned();
        line.split_whitespace()
            .find_map(|w| w.strip_prefix(key).and_then(|v| v.strip_prefix('=')).map(str::to_owned))
    }
}

fn item(
    group: &'static str,
    name: &'static str,
    value: String,
    meaning: String,
    fix: &str,
    ok: bool,
) -> Item {
    Item { group, name, value, meaning, fix: if ok { String::new() } else { fix.to_owned() }, ok }
}

/// Every item, for a loop at `rate_hz`.
pub fn report(root: &Path, p: &Probe, rate_hz: f64) -> super::Report {
    let s = Sys(root.to_owned());
    let period_us = 1e6 / rate_hz;
    let mut items = cpus(&s, p);
    items.extend(scheduling(&s, p));
    items.extend(timers(&s, p, period_us));
    items.extend(memory(&s, p));
    items.extend(interference(&s, p, period_us));
    super::Report { rate_hz, items }
}

fn cpus(s: &Sys, p: &Probe) -> Vec<Item> {
    let online = s.list("sys/devices/system/cpu/online").unwrap_or_default();
    let n = p.cpus.len();
    let mut siblings: Vec<Vec<usize>> = Vec::new();
    for c in &online {
        if let Some(l) =
            s.list(&format!("sys/devices/system/cpu/cpu{c}/topology/thread_siblings_list"))
        {
            if l.len() > 1 && !siblings.contains(&l) {
                siblings.push(l);
            }
        }
    }
    let nodes =
        s.entries("sys/devices/system/node").iter().filter(|e| e.starts_with("node")).count();
    let isolated = s.list("sys/devices/system/cpu/isolated").unwrap_or_default();
    let nohz = s.cmdline("nohz_full");
    let nocbs = s.cmdline("rcu_nocbs");
    let cross = n >= 2;
    vec![
        item("cpus", "cpus", format!("{} online ({}); this process may use {n}: {}", online.len(), format_list(&online), format_list(&p.cpus)),
            format!("{} cross-core loop(s) of 2 cores or {} dedicated loop(s) of 4 fit without sharing a core", n / 2, n / 4),
            "taskset -c LIST rotorloop …, or rotorloop run --cpus LIST (within the CPU set)", cross),
        item("cpus", "smt", match siblings.is_empty() { true => "no SMT siblings".into(), false => format!("{} physical cores with hyperthreads: {}", siblings.len(), siblings.iter().map(|g| format_list(g)).collect::<Vec<_>>().join(" ")) },
            "the placement gives one role per physical core while they suffice (a sibling's load slows its twin)".into(), "", true),
        item("cpus", "numa", format!("{} node(s)", nodes.max(1)), "a loop's cores on one node keep its shared memory local".into(), "", true),
        item("cpus", "isolated", format!("isolated CPUs: {}", format_list(&isolated)),
            match isolated.is_empty() { true => "every core also runs the kernel's and other processes' work; a loop's tick shares it".into(), false => "the loops are placed on the isolated CPUs first".into() },
            "isolcpus=LIST on the kernel command line (reboot)", !isolated.is_empty()),
        item("cpus", "nohz_full", nohz.clone().unwrap_or_else(|| "not set".into()),
            "without it each busy core takes the scheduler tick (a few µs every 1–4 ms)".into(), "nohz_full=LIST on the kernel command line (reboot)", nohz.is_some()),
        item("cpus", "rcu_nocbs", nocbs.clone().unwrap_or_else(|| "not set".into()),
            "without it RCU callbacks run on the loop's cores".into(), "rcu_nocbs=LIST on the kernel command line (reboot)", nocbs.is_some()),
    ]
}

/// Why a `SCHED_FIFO` request was refused, from what may refuse it.
fn fifo_reason(s: &Sys, p: &Probe) -> String {
    let mut why = Vec::new();
    let cap = s
        .read("proc/self/status")
        .and_then(|t| {
            t.lines().find_map(|l| l.strip_prefix("CapEff:").map(|v| v.trim().to_owned()))
        })
        .and_then(|v| u64::from_str_radix(&v, 16).ok());
    let nice = cap.map(|c| c & (1 << 23) != 0);
    if p.rtprio_limit == Some(0) && nice != Some(true) {
        why.push("RLIMIT_RTPRIO is 0 and CAP_SYS_NICE is not held".to_owned());
    }
    if let Some(rt) = cgroup_rt_runtime(s) {
        if rt == 0 {
            why.push(
                "this process's cgroup gives real-time tasks no runtime (cpu.rt_runtime_us 0)"
                    .into(),
            );
        }
    }
    if nice == Some(false) && p.euid != 0 {
        why.push("not root and without CAP_SYS_NICE".into());
    }
    if let Some(group) = cgroup_v2_group(s).filter(|_| cgroup_rt_runtime(s).is_none()) {
        why.push(format!(
            "this process is in the cgroup v2 group {group}: where the kernel has real-time \
             group scheduling (CONFIG_RT_GROUP_SCHED), a real-time task is refused outside \
             the root group (cgroup v2 has no cpu.rt_runtime_us to grant it runtime)"
        ));
    }
    if why.is_empty() {
        why.push("none of RLIMIT_RTPRIO, cpu.rt_runtime_us or the capabilities explains it (a seccomp filter or a security module may)".into());
    }
    why.join("; ")
}

/// `cpu.rt_runtime_us` of this process's cgroup (v1 `cpu` controller), if there is one
/// (cgroup v2 has none: [`cgroup_v2_group`]).
fn cgroup_rt_runtime(s: &Sys) -> Option<i64> {
    let groups = s.read("proc/self/cgroup")?;
    let path = groups.lines().find_map(|l| {
        let mut f = l.splitn(3, ':');
        let (_, ctrl, path) = (f.next()?, f.next()?, f.next()?);
        ctrl.split(',').any(|c| c == "cpu").then(|| path.trim_start_matches('/').to_owned())
    })?;
    ["sys/fs/cgroup/cpu", "sys/fs/cgroup/cpu,cpuacct"].iter().find_map(|base| {
        let rel = if path.is_empty() {
            format!("{base}/cpu.rt_runtime_us")
        } else {
            format!("{base}/{path}/cpu.rt_runtime_us")
        };
        s.read(&rel).and_then(|v| v.parse().ok())
    })
}

/// This process's cgroup v2 group (the `0::PATH` line of `/proc/self/cgroup`) where it is
/// not the root group (`/`) and the `cpu` controller is not on a v1 hierarchy.
fn cgroup_v2_group(s: &Sys) -> Option<String> {
    let groups = s.read("proc/self/cgroup")?;
    let v1_cpu = groups
        .lines()
        .any(|l| l.split(':').nth(1).is_some_and(|c| c.split(',').any(|c| c == "cpu")));
    let path = groups.lines().find_map(|l| l.strip_prefix("0::"))?;
    (!v1_cpu && path != "/").then(|| path.to_owned())
}

fn scheduling(s: &Sys, p: &Probe) -> Vec<Item> {
    let fifo = match p.fifo {
        Ok(()) => item("scheduling", "sched_fifo", "SCHED_FIFO available (granted to a child)".into(),
            "--rt-priority P runs the roles above every normal task".into(), "", true),
        Err(e) => item("scheduling", "sched_fifo",
            format!("SCHED_FIFO not available ({}): {}", std::io::Error::from_raw_os_error(e), fifo_reason(s, p)),
            "--rt-priority is refused with a warning: the loop runs at normal priority, shared with every other task".into(),
            "ulimit -r 99 (or `@realtime - rtprio 99` in /etc/security/limits.conf), or run as root; in a container: docker run --cap-add SYS_NICE --ulimit rtprio=99 --cpu-rt-runtime=950000", false),
    };
    let runtime = s.read("proc/sys/kernel/sched_rt_runtime_us").and_then(|v| v.parse::<i64>().ok());
    let period = s.read("proc/sys/kernel/sched_rt_period_us").and_then(|v| v.parse::<i64>().ok());
    let throttle = match (runtime, period) {
        (Some(-1), _) => item(
            "scheduling",
            "rt_throttling",
            "off (sched_rt_runtime_us -1)".into(),
            "a spinning SCHED_FIFO role can starve its core's other tasks for ever".into(),
            "",
            true,
        ),
        (Some(r), Some(per)) => item(
            "scheduling",
            "rt_throttling",
            format!("real-time tasks get {r} µs of every {per} µs"),
            format!(
                "a SCHED_FIFO role that spins is stopped for {} µs each period (every tick then is late once a period)",
                per - r
            ),
            "echo -1 > /proc/sys/kernel/sched_rt_runtime_us (only with a spare core)",
            true,
        ),
        _ => item(
            "scheduling",
            "rt_throttling",
            "unknown".into(),
            "no /proc/sys/kernel/sched_rt_runtime_us".into(),
            "",
            true,
        ),
    };
    let version = s.read("proc/version").unwrap_or_default();
    let rt =
        s.read("sys/kernel/realtime").as_deref() == Some("1") || version.contains("PREEMPT_RT");
    let model = match (
        rt,
        s.cmdline("preempt"),
        version.contains("PREEMPT_DYNAMIC"),
        version.contains("PREEMPT"),
    ) {
        (true, _, _, _) => "PREEMPT_RT".to_owned(),
        (false, Some(m), _, _) => format!("preempt={m} (command line)"),
        (false, None, true, _) => "PREEMPT_DYNAMIC (its default, usually voluntary)".into(),
        (false, None, false, true) => "PREEMPT".into(),
        _ => "no forced preemption".into(),
    };
    let preempt = item(
        "scheduling",
        "preemption",
        model,
        match rt {
            true => "the kernel can be preempted almost everywhere: bounded wake-up latency".into(),
            false => {
                "a wake-up can wait for a kernel section to end (tens to hundreds of µs at worst)"
                    .into()
            }
        },
        "a PREEMPT_RT kernel, or preempt=full on the command line of a PREEMPT_DYNAMIC one",
        rt,
    );
    vec![fifo, throttle, preempt]
}

fn timers(s: &Sys, p: &Probe, period_us: f64) -> Vec<Item> {
    let clock = s
        .read("sys/devices/system/clocksource/clocksource0/current_clocksource")
        .unwrap_or_else(|| "unknown".into());
    let good = ["tsc", "arch_sys_counter"].contains(&clock.as_str());
    let driver =
        s.read("sys/devices/system/cpu/cpuidle/current_driver").unwrap_or_else(|| "none".into());
    let cpu = p.cpus.first().copied().unwrap_or(0);
    let states: Vec<(String, u64)> = s
        .entries(&format!("sys/devices/system/cpu/cpu{cpu}/cpuidle"))
        .iter()
        .filter(|e| e.starts_with("state"))
        .filter_map(|st| {
            let d = format!("sys/devices/system/cpu/cpu{cpu}/cpuidle/{st}");
            Some((s.read(&format!("{d}/name"))?, s.read(&format!("{d}/latency"))?.parse().ok()?))
        })
        .collect();
    let deepest = states.iter().map(|(_, l)| *l).max().unwrap_or(0);
    let listed: Vec<String> = states.iter().map(|(n, l)| format!("{n} {l} µs")).collect();
    let gov = s.read(&format!("sys/devices/system/cpu/cpu{cpu}/cpufreq/scaling_governor"));
    vec![
        item("timers", "clocksource", clock.clone(), match good { true => "reading the clock costs tens of ns".into(), false => "reading the clock may cost µs (a timestamp per stage of every tick)".into() }, "echo tsc > /sys/devices/system/clocksource/clocksource0/current_clocksource", good),
        item("timers", "cpuidle", format!("driver {driver}; states of CPU {cpu}: {}", if listed.is_empty() { "none".into() } else { listed.join(", ") }),
            format!("an idle core takes up to {deepest} µs to wake, {:.1} % of a {period_us:.0} µs tick", 100.0 * deepest as f64 / period_us),
            "rotorloop run --cpu-dma-latency 0 (root), or idle=poll / intel_idle.max_cstate=1 on the command line", deepest as f64 <= 0.02 * period_us),
        match p.dma_latency {
            Ok(()) => item("timers", "cpu_dma_latency", "/dev/cpu_dma_latency can be held".into(), "--cpu-dma-latency 0 keeps idle cores polling for a run".into(), "", true),
            Err(e) => item("timers", "cpu_dma_latency", format!("/dev/cpu_dma_latency cannot be held ({})", std::io::Error::from_raw_os_error(e)),
                "--cpu-dma-latency is refused with a warning: idle states stay as they are".into(), "run as root, or chmod o+w /dev/cpu_dma_latency", false),
        },
        item("timers", "governor", gov.clone().unwrap_or_else(|| "no cpufreq (a VM, or fixed frequency)".into()),
            "a governor other than performance lowers the clock of an idle core; the tick after idling runs slower".into(),
            "cpupower frequency-set -g performance", gov.as_deref().is_none_or(|g| g == "performance")),
    ]
}

fn memory(s: &Sys, p: &Probe) -> Vec<Item> {
    let mlock_ok = p.euid == 0 || p.memlock_limit.is_none();
    let thp =
        s.read("sys/kernel/mm/transparent_hugepage/enabled").unwrap_or_else(|| "unknown".into());
    let thp_mode =
        thp.split('[').nth(1).and_then(|r| r.split(']').next()).unwrap_or("unknown").to_owned();
    let swap_lines = s
        .read("proc/swaps")
        .map_or(0, |t| t.lines().skip(1).filter(|l| !l.trim().is_empty()).count());
    let mb = |b: u64| b as f64 / 1e6;
    vec![
        item(
            "memory",
            "mlockall",
            match p.memlock_limit {
                None => "RLIMIT_MEMLOCK unlimited".into(),
                Some(l) => format!(
                    "RLIMIT_MEMLOCK {} KiB{}",
                    l / 1024,
                    if p.euid == 0 { " (root: not bound by it)" } else { "" }
                ),
            },
            match mlock_ok {
                true => "--mlock locks every role's memory: no page fault in a tick".into(),
                false => {
                    "--mlock fails with a warning beyond the limit: a page fault can stall a tick"
                        .into()
                }
            },
            "ulimit -l unlimited (or `@realtime - memlock unlimited` in /etc/security/limits.conf)",
            mlock_ok,
        ),
        item(
            "memory",
            "thp",
            thp_mode.clone(),
            "`always`: the kernel may compact memory to make huge pages, stalling a fault for ms"
                .into(),
            "echo madvise > /sys/kernel/mm/transparent_hugepage/enabled",
            thp_mode != "always",
        ),
        item(
            "memory",
            "swap",
            format!("{swap_lines} swap device(s)"),
            "with swap a role's page may be swapped out and faulted back in a tick, unless --mlock"
                .into(),
            "swapoff -a, or --mlock",
            swap_lines == 0,
        ),
        match p.shm_free {
            Some(free) => item(
                "memory",
                "shm",
                format!(
                    "/dev/shm {:.0} MB free; a run of this rate and length keeps {:.0} MB there",
                    mb(free),
                    mb(p.shm_need)
                ),
                "the flight rings live there while the run goes on".into(),
                "mount -o remount,size=2G /dev/shm (a container: --shm-size)",
                free >= p.shm_need,
            ),
            None => item(
                "memory",
                "shm",
                "/dev/shm cannot be asked".into(),
                "iceoryx2 and the flight rings need it".into(),
                "mount -t tmpfs tmpfs /dev/shm",
                false,
            ),
        },
    ]
}

fn interference(s: &Sys, p: &Probe, period_us: f64) -> Vec<Item> {
    let irqbalance = s
        .entries("proc")
        .iter()
        .filter(|e| e.bytes().all(|b| b.is_ascii_digit()))
        .any(|pid| s.read(&format!("proc/{pid}/comm")).as_deref() == Some("irqbalance"));
    let irqs = s.entries("proc/irq");
    let mut hitting = 0;
    for irq in irqs.iter().filter(|e| e.bytes().all(|b| b.is_ascii_digit())) {
        let cpus = s.list(&format!("proc/irq/{irq}/smp_affinity_list")).unwrap_or_default();
        if cpus.iter().any(|c| p.cpus.contains(c)) {
            hitting += 1;
        }
    }
    let stat = s.read("proc/stat").unwrap_or_default();
    let fields: Vec<u64> = stat
        .lines()
        .next()
        .unwrap_or_default()
        .split_whitespace()
        .skip(1)
        .filter_map(|v| v.parse().ok())
        .collect();
    let total: u64 = fields.iter().take(8).sum();
    let steal = fields.get(7).copied().unwrap_or(0);
    let share = if total > 0 { 100.0 * steal as f64 / total as f64 } else { 0.0 };
    vec![
        item(
            "interference",
            "irqbalance",
            if irqbalance { "running".into() } else { "not running".into() },
            "irqbalance moves interrupts onto any core, the loop's among them, every 10 s".into(),
            "systemctl stop irqbalance (then set IRQ affinities by hand)",
            !irqbalance,
        ),
        item(
            "interference",
            "irq_affinity",
            format!(
                "{hitting} of {} IRQs may fire on the run's CPUs ({})",
                irqs.iter().filter(|e| e.bytes().all(|b| b.is_ascii_digit())).count(),
                format_list(&p.cpus)
            ),
            format!(
                "an interrupt on a loop's core delays its tick by its handler's time (µs) within the {period_us:.0} µs period"
            ),
            "echo OTHER_CPUS > /proc/irq/N/smp_affinity_list for each IRQ (root)",
            hitting == 0,
        ),
        item(
            "interference",
            "steal",
            format!("{share:.2} % of CPU time stolen since boot (/proc/stat)"),
            "a hypervisor running another guest on this vCPU: the loop loses that time in bursts"
                .into(),
            "a dedicated host or pinned vCPUs",
            share < 0.1,
        ),
    ]
}

#[cfg(test)]
mod tests;
