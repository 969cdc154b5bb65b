//! The doctor's items from a fixture of this development machine's `/proc` and `/sys`
//! (`tests/fixtures/doctor/firecracker-2vcpu`, its README says where from), and from
//! copies of it changed to another machine; the system calls faked in the [`Probe`].

use std::path::{Path, PathBuf};

use super::*;

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/doctor/firecracker-2vcpu")
}

/// What this machine's system calls said (root, SCHED_FIFO granted, `RLIMIT_RTPRIO` 0,
/// 8 MiB of `RLIMIT_MEMLOCK`).
fn granted() -> Probe {
    Probe {
        cpus: vec![0, 1],
        fifo: Ok(()),
        rtprio_limit: Some(0),
        memlock_limit: Some(8 << 20),
        euid: 0,
        dma_latency: Ok(()),
        shm_free: Some(24_000_000_000),
        shm_need: 80_000_000,
    }
}

/// A copy of the fixture with `changes` (path, contents) written over it.
fn changed(name: &str, changes: &[(&str, &str)]) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("rotorloop-doctor-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    copy(&fixture(), &dir);
    for (rel, text) in changes {
        let p = dir.join(rel);
        std::fs::create_dir_all(p.parent().expect("a parent")).expect("dir");
        std::fs::write(p, text).expect("write");
    }
    dir
}

fn copy(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).expect("dir");
    for e in std::fs::read_dir(from).expect("fixture").flatten() {
        let target = to.join(e.file_name());
        match e.file_type().expect("type").is_dir() {
            true => copy(&e.path(), &target),
            false => drop(std::fs::copy(e.path(), target).expect("copy")),
        }
    }
}

/// The fixture read as this machine is: 2 CPUs, no SMT, one node, nothing isolated,
/// PREEMPT_DYNAMIC, tsc, the haltpoll driver with its two states, THP on madvise, no
/// swap, RT throttling at 950000 of 1000000 µs, and its IRQs on both CPUs.
#[test]
fn this_machine_is_read_from_its_files() {
    let r = report(&fixture(), &granted(), 1000.0);
    let v = |name: &str| r.item(name).unwrap_or_else(|| panic!("{name}")).value.clone();
    assert!(v("cpus").starts_with("2 online (0-1); this process may use 2: 0-1"), "{}", v("cpus"));
    assert_eq!(v("smt"), "no SMT siblings");
    assert_eq!(v("numa"), "1 node(s)");
    assert_eq!(v("isolated"), "isolated CPUs: -");
    assert_eq!(v("nohz_full"), "not set");
    assert_eq!(v("preemption"), "PREEMPT_DYNAMIC (its default, usually voluntary)");
    assert_eq!(v("rt_throttling"), "real-time tasks get 950000 µs of every 1000000 µs");
    assert_eq!(v("clocksource"), "tsc");
    assert_eq!(v("cpuidle"), "driver haltpoll; states of CPU 0: POLL 0 µs, haltpoll idle 1 µs");
    assert_eq!(v("thp"), "madvise");
    assert_eq!(v("swap"), "0 swap device(s)");
    assert_eq!(v("irq_affinity"), "5 of 5 IRQs may fire on the run's CPUs (0-1)");
    assert!(v("steal").ends_with("% of CPU time stolen since boot (/proc/stat)"));
    assert!(r.item("sched_fifo").expect("fifo").ok);
    // Every item says what it means, and a not-ok one how to change it.
    for i in &r.items {
        assert!(!i.meaning.is_empty(), "{i:?}");
        assert_eq!(i.ok, i.fix.is_empty(), "{i:?}");
    }
}

/// The issue's container: root with `RLIMIT_RTPRIO` 0 and without `CAP_SYS_NICE`, and a
/// cgroup that gives real-time tasks no runtime. The refused `sched_setscheduler` names
/// both, says what it means for a run and how to change it.
#[test]
fn a_refused_sched_fifo_names_its_reasons() {
    let dir = changed(
        "fifo",
        &[
            ("proc/self/status", "Name:\trotorloop\nCapEff:\t0000000000000000\n"),
            ("sys/fs/cgroup/cpu/cpu.rt_runtime_us", "0\n"),
        ],
    );
    let mut p = granted();
    p.fifo = Err(libc::EPERM);
    p.euid = 1000;
    let r = report(&dir, &p, 1000.0);
    std::fs::remove_dir_all(&dir).expect("clean up");
    let fifo = r.item("sched_fifo").expect("fifo");
    assert!(!fifo.ok);
    assert!(
        fifo.value.starts_with("SCHED_FIFO not available (Operation not permitted"),
        "{}",
        fifo.value
    );
    for reason in ["RLIMIT_RTPRIO is 0", "cpu.rt_runtime_us 0", "without CAP_SYS_NICE"] {
        assert!(fifo.value.contains(reason), "{reason}: {}", fifo.value);
    }
    assert!(fifo.meaning.contains("normal priority"), "{}", fifo.meaning);
    assert!(fifo.fix.contains("ulimit -r"), "{}", fifo.fix);
    // A pure cgroup v2 machine, the process in a group of its own: that group is named as
    // a possible cause (v2 has no cpu.rt_runtime_us); in the root group it is not.
    for (group, named) in [("/user.slice/loop.scope", true), ("/", false)] {
        let dir = changed("fifo-v2", &[("proc/self/cgroup", &format!("0::{group}\n"))]);
        let mut p = granted();
        p.fifo = Err(libc::EPERM);
        let r = report(&dir, &p, 1000.0);
        std::fs::remove_dir_all(&dir).expect("clean up");
        let v = r.item("sched_fifo").expect("fifo").value.clone();
        let says = v.contains(&format!("cgroup v2 group {group}:"));
        assert_eq!(says, named, "{group}: {v}");
        assert_eq!(v.contains("none of RLIMIT_RTPRIO"), !named, "{group}: {v}");
    }
    // With the capability and a runtime, the refusal is still said, its cause unknown.
    let mut p = granted();
    p.fifo = Err(libc::EPERM);
    let r = report(&fixture(), &p, 1000.0);
    assert!(r.item("sched_fifo").expect("fifo").value.contains("none of RLIMIT_RTPRIO"));
}

/// A faked CPU set and another machine's files: 16 CPUs as 8 physical cores with two
/// hyperthreads, isolated 8–15, nohz_full, PREEMPT_RT, a deep idle state, the powersave
/// governor, THP always, swap, irqbalance running, and the run's CPUs free of IRQs.
#[test]
fn another_machine_is_named_item_by_item() {
    let mut files: Vec<(String, String)> = vec![
        ("sys/devices/system/cpu/online".into(), "0-15\n".into()),
        ("sys/devices/system/cpu/isolated".into(), "8-15\n".into()),
        ("proc/cmdline".into(), "ro nohz_full=8-15 rcu_nocbs=8-15 preempt=full\n".into()),
        ("proc/version".into(), "Linux version 6.6.0-rt #1 SMP PREEMPT_RT\n".into()),
        ("sys/kernel/realtime".into(), "1\n".into()),
        ("sys/devices/system/cpu/cpu8/cpuidle/state2/name".into(), "C6\n".into()),
        ("sys/devices/system/cpu/cpu8/cpuidle/state2/latency".into(), "133\n".into()),
        ("sys/devices/system/cpu/cpu8/cpufreq/scaling_governor".into(), "powersave\n".into()),
        ("sys/kernel/mm/transparent_hugepage/enabled".into(), "[always] madvise never\n".into()),
        ("proc/swaps".into(), "Filename Type Size Used Priority\n/swap file 100 0 -2\n".into()),
        ("proc/4242/comm".into(), "irqbalance\n".into()),
        ("proc/irq/24/smp_affinity_list".into(), "0-7\n".into()),
    ];
    for c in 0..16 {
        let sib = format!("{},{}\n", c % 8, c % 8 + 8);
        files.push((format!("sys/devices/system/cpu/cpu{c}/topology/thread_siblings_list"), sib));
    }
    let refs: Vec<(&str, &str)> = files.iter().map(|(a, b)| (a.as_str(), b.as_str())).collect();
    let dir = changed("other", &refs);
    for irq in ["25", "26", "28", "29"] {
        std::fs::remove_dir_all(dir.join("proc/irq").join(irq)).expect("rm irq");
    }
    let mut p = granted();
    p.cpus = (8..16).collect();
    p.shm_free = Some(10_000_000);
    let r = report(&dir, &p, 1000.0);
    std::fs::remove_dir_all(&dir).expect("clean up");
    let get = |n: &str| r.item(n).unwrap_or_else(|| panic!("{n}")).clone();
    assert!(get("cpus").meaning.starts_with("4 cross-core loop(s) of 2 cores or 2 dedicated"));
    assert!(
        get("smt").value.starts_with("8 physical cores with hyperthreads: 0,8 1,9"),
        "{}",
        get("smt").value
    );
    assert!(get("isolated").ok && get("isolated").value == "isolated CPUs: 8-15");
    assert_eq!(get("nohz_full").value, "8-15");
    assert!(get("preemption").ok && get("preemption").value == "PREEMPT_RT");
    let idle = get("cpuidle");
    assert!(
        !idle.ok && idle.meaning.starts_with("an idle core takes up to 133 µs to wake, 13.3 %"),
        "{idle:?}"
    );
    assert!(!get("governor").ok && get("governor").value == "powersave");
    assert!(!get("thp").ok && get("thp").value == "always");
    assert!(!get("swap").ok);
    assert!(!get("irqbalance").ok);
    assert!(get("irq_affinity").ok, "{:?}", get("irq_affinity"));
    assert!(!get("shm").ok && get("shm").value.contains("keeps 80 MB"), "{:?}", get("shm"));
}
