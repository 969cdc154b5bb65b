//! Which CPUs a run or a bench's loops get: CPU lists (`0-3,8`), the process's own CPU
//! set (`sched_getaffinity`, so a cgroup's cpuset or `taskset` is respected), the
//! kernel's isolated CPUs and the SMT siblings, and [`place`]: N loops on disjoint core
//! sets, a pure function of that topology, the loop count and the shape of a loop.
//!
//! The order cores are handed out in: the kernel's isolated CPUs first; then the others,
//! CPU 0 last (it takes most of the housekeeping: timers, RCU, unbound work). With SMT,
//! one role per physical core: the first hyperthread of every physical core is handed
//! out before any sibling, and the siblings of cores in use stay idle while the physical
//! cores suffice. When they do not, the siblings are used, both hyperthreads of a
//! physical core going to the same loop. When even the hyperthreads do not suffice, the
//! loops are placed as asked, round robin over the cores, and the placement says which
//! cores carry roles of more than one loop.
//!
//! A room beneath `run`, `study` and `doctor`, which all read the machine's CPUs through it.

use std::path::Path;

use rotorloop_common::role::UsageError;

/// The largest CPU number a list may name.
pub const MAX_CPU: usize = 4095;

/// Parses a CPU list as the kernel writes it (`0-3,8,10-11`): sorted, without repeats.
/// `flag` names the field in the refusal.
pub fn parse_list(s: &str, flag: &str) -> Result<Vec<usize>, UsageError> {
    let bad = |part: &str, why: &str| {
        UsageError(format!(
            "{flag} `{part}` is not allowed: {why} (a CPU list such as 0-3,8; CPUs 0 to {MAX_CPU})"
        ))
    };
    let mut cpus = Vec::new();
    for part in s.trim().split(',').map(str::trim) {
        if part.is_empty() {
            return Err(bad(s, "an empty entry"));
        }
        let (lo, hi) = part.split_once('-').unwrap_or((part, part));
        let num = |v: &str| v.parse::<usize>().ok().filter(|c| *c <= MAX_CPU);
        let (Some(lo), Some(hi)) = (num(lo), num(hi)) else {
            return Err(bad(part, "not a CPU number or range"));
        };
        if lo > hi {
            return Err(bad(part, "a range from high to low"));
        }
        cpus.extend(lo..=hi);
    }
    cpus.sort_unstable();
    cpus.dedup();
    Ok(cpus)
}

/// Writes a CPU list as the kernel does (`0-3,8`); `-` for none.
pub fn format_list(cpus: &[usize]) -> String {
    let mut sorted = cpus.to_vec();
    sorted.sort_unstable();
    sorted.dedup();
    let mut parts: Vec<String> = Vec::new();
    let mut i = 0;
    while i < sorted.len() {
        let mut j = i;
        while j + 1 < sorted.len() && sorted[j + 1] == sorted[j] + 1 {
            j += 1;
        }
        parts.push(match j > i {
            true => format!("{}-{}", sorted[i], sorted[j]),
            false => sorted[i].to_string(),
        });
        i = j + 1;
    }
    match parts.is_empty() {
        true => "-".to_owned(),
        false => parts.join(","),
    }
}

/// The CPUs this process may run on (`sched_getaffinity`); every CPU the machine has
/// online when the call fails.
pub fn allowed_now() -> Vec<usize> {
    // SAFETY: sched_getaffinity fills the zeroed set it is given, of the size given.
    let mut set: libc::cpu_set_t = unsafe { std::mem::zeroed() };
    let ok = unsafe { libc::sched_getaffinity(0, size_of::<libc::cpu_set_t>(), &mut set) } == 0;
    if !ok {
        let n = std::thread::available_parallelism().map_or(1, |n| n.get());
        return (0..n).collect();
    }
    // SAFETY: CPU_ISSET reads the set filled above.
    (0..libc::CPU_SETSIZE as usize).filter(|c| unsafe { libc::CPU_ISSET(*c, &set) }).collect()
}

/// A `cpu_set_t` of `cpus`, made before a fork so that the child only calls
/// `sched_setaffinity` (async-signal-safe) with it.
pub fn cpu_set(cpus: &[usize]) -> libc::cpu_set_t {
    // SAFETY: a zeroed cpu_set_t is the empty set; CPU_SET writes inside it.
    let mut set: libc::cpu_set_t = unsafe { std::mem::zeroed() };
    for &c in cpus.iter().filter(|c| **c < libc::CPU_SETSIZE as usize) {
        unsafe { libc::CPU_SET(c, &mut set) };
    }
    set
}

/// What [`place`] needs to know of the machine.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Topology {
    /// The CPUs the process may use (its CPU set, or a run's `--cpus`), sorted.
    pub allowed: Vec<usize>,
    /// The kernel's isolated CPUs (`isolcpus=`, `/sys/devices/system/cpu/isolated`).
    pub isolated: Vec<usize>,
    /// The hyperthreads of each physical core (`thread_siblings_list`), each sorted; a CPU
    /// in none of them is a core of its own.
    pub siblings: Vec<Vec<usize>>,
}

impl Topology {
    /// This machine, as seen from `sys` (`/sys` on a live system; a fixture's copy in
    /// tests), restricted to `allowed`.
    pub fn read(sys: &Path, allowed: Vec<usize>) -> Self {
        let cpu = sys.join("devices/system/cpu");
        let list =
            |p: &Path| std::fs::read_to_string(p).ok().and_then(|t| parse_list(&t, "sysfs").ok());
        let isolated = list(&cpu.join("isolated")).unwrap_or_default();
        let mut siblings: Vec<Vec<usize>> = Vec::new();
        for c in &allowed {
            let path = cpu.join(format!("cpu{c}/topology/thread_siblings_list"));
            if let Some(s) = list(&path).filter(|s| s.len() > 1) {
                if !siblings.contains(&s) {
                    siblings.push(s);
                }
            }
        }
        Self { allowed, isolated, siblings }
    }

    /// This process's CPU set on this machine.
    pub fn this_process() -> Self {
        Self::read(Path::new("/sys"), allowed_now())
    }

    /// The same machine restricted to `cpus` (a run's `--cpus`).
    pub fn within(&self, cpus: &[usize]) -> Self {
        Self { allowed: cpus.to_vec(), ..self.clone() }
    }

    /// Physical cores: each a list of its allowed hyperthreads, first one first, in the
    /// order they are handed out (isolated first, CPU 0 last, then by number).
    fn cores(&self) -> Vec<Vec<usize>> {
        let mut cores: Vec<Vec<usize>> = Vec::new();
        for &c in &self.allowed {
            if cores.iter().any(|k| k.contains(&c)) {
                continue;
            }
            let group = self.siblings.iter().find(|s| s.contains(&c));
            let mut threads: Vec<usize> = match group {
                Some(g) => g.iter().copied().filter(|t| self.allowed.contains(t)).collect(),
                None => vec![c],
            };
            threads.sort_unstable();
            cores.push(threads);
        }
        let key = |k: &Vec<usize>| (!self.isolated.contains(&k[0]), k.contains(&0), k[0]);
        cores.sort_by_key(key);
        cores
    }
}

/// The shape of one loop: how many cores it takes and which role goes on which.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Shape {
    /// All four roles on one core.
    SameCore,
    /// Two cores: plant and monitor on the first, controller and reference on the second.
    CrossCore,
    /// Four cores, a role on each (`--preset dedicated`).
    Dedicated,
    /// A share of the cores, the roles unpinned inside it.
    Unpinned,
}

impl Shape {
    /// The shape of a bench placement (`same-core`, `cross-core`, `dedicated`, anything
    /// else unpinned).
    pub fn of_placement(placement: &str) -> Self {
        match placement {
            "same-core" => Self::SameCore,
            "cross-core" => Self::CrossCore,
            "dedicated" => Self::Dedicated,
            _ => Self::Unpinned,
        }
    }

    /// Cores a loop of this shape takes when `n` loops share `cpus` CPUs (unpinned: an
    /// equal share, at least one).
    pub fn per_loop(self, cpus: usize, n: usize) -> usize {
        match self {
            Self::SameCore => 1,
            Self::CrossCore => 2,
            Self::Dedicated => 4,
            Self::Unpinned => (cpus / n.max(1)).max(1),
        }
    }
}

/// One loop's cores.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LoopCores {
    /// The loop's CPU set (every role's affinity before it pins itself).
    pub cpus: Vec<usize>,
    /// The cores of plant, controller, reference and monitor; `None`: unpinned in `cpus`.
    pub roles: Option<[usize; 4]>,
}

impl LoopCores {
    /// The `--pin` of this loop, if its roles are pinned.
    pub fn pin(&self) -> Option<String> {
        self.roles.map(|[p, c, r, m]| format!("plant={p},controller={c},reference={r},monitor={m}"))
    }
}

/// Where N loops go, and what is said of it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Placement {
    /// Each loop's cores.
    pub loops: Vec<LoopCores>,
    /// Whether some core carries roles of more than one loop.
    pub shared: bool,
    /// Sentences for a report: what was done with SMT siblings, which cores are shared.
    pub notes: Vec<String>,
}

/// What is done with SMT sibling hyperthreads.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum Smt {
    /// One role per physical core: the siblings stay idle while the physical cores
    /// suffice (then used, both hyperthreads of a core to the same loop).
    #[default]
    Idle,
    /// Every hyperthread a core of its own from the start, both hyperthreads of a
    /// physical core to the same loop: more loops apart, each sharing its cores' pipelines.
    Use,
}

/// Places `n` loops of `shape` on the cores of `t` (module docs: the order, SMT, sharing),
/// the siblings left idle while the physical cores suffice ([`Smt::Idle`]).
pub fn place(t: &Topology, n: usize, shape: Shape) -> Placement {
    place_smt(t, n, shape, Smt::Idle)
}

/// [`place`], with `smt` saying what is done with sibling hyperthreads.
pub fn place_smt(t: &Topology, n: usize, shape: Shape, mode: Smt) -> Placement {
    let n = n.max(1);
    let cores = t.cores();
    let physical: Vec<usize> = cores.iter().map(|k| k[0]).collect();
    let threads: usize = cores.iter().map(Vec::len).sum();
    let per_loop = shape.per_loop(threads, n);
    let need = n * per_loop;
    let mut notes = Vec::new();
    let smt = threads > physical.len();
    let order: Vec<usize> = if smt && mode == Smt::Use {
        notes.push(format!(
            "SMT: every hyperthread used as a core (--smt use): {threads} CPUs on {} physical \
             cores, both hyperthreads of a physical core given to the same loop",
            physical.len()
        ));
        cores.iter().flatten().copied().collect()
    } else if need <= physical.len() || !smt {
        if smt {
            notes.push(format!(
                "SMT: one role per physical core; the sibling hyperthreads of the {} physical \
                 cores ({} CPUs) are left idle",
                physical.len(),
                threads - physical.len()
            ));
        }
        physical
    } else {
        notes.push(format!(
            "SMT: {need} cores needed and {} physical cores: sibling hyperthreads used, both \
             hyperthreads of a physical core given to the same loop",
            physical.len()
        ));
        cores.iter().flatten().copied().collect()
    };
    let len = order.len().max(1);
    let loops: Vec<LoopCores> = (0..n)
        .map(|i| {
            let mine: Vec<usize> = (0..per_loop)
                .map(|j| order.get((i * per_loop + j) % len).copied().unwrap_or(0))
                .collect();
            let roles = match shape {
                Shape::SameCore => Some([mine[0]; 4]),
                Shape::CrossCore => Some([mine[0], mine[1], mine[1], mine[0]]),
                Shape::Dedicated => Some([mine[0], mine[1], mine[2], mine[3]]),
                Shape::Unpinned => None,
            };
            let mut cpus = mine;
            cpus.sort_unstable();
            cpus.dedup();
            LoopCores { cpus, roles }
        })
        .collect();
    let shared = need > len;
    if shared {
        notes.push(sharing_note(n, per_loop, &order, &loops));
    }
    Placement { loops, shared, notes }
}

/// "cores shared: …": how many loops each core carries.
fn sharing_note(n: usize, per_loop: usize, order: &[usize], loops: &[LoopCores]) -> String {
    let carried: Vec<String> = order
        .iter()
        .map(|c| {
            let k = loops.iter().filter(|l| l.cpus.contains(c)).count();
            format!("CPU {c}: {k}")
        })
        .collect();
    format!(
        "cores shared: {n} loops of {per_loop} core(s) need {} and {} are available, so the \
         loops are placed round robin over the cores and some cores carry roles of several \
         loops (loops per CPU: {})",
        n * per_loop,
        order.len(),
        carried.join(", ")
    )
}

/// The CPUs a process may run on, as the kernel says (`Cpus_allowed_list` of
/// `/proc/PID/status`).
pub fn allowed_of(pid: u32) -> Option<String> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status.lines().find_map(|l| l.strip_prefix("Cpus_allowed_list:")).map(|v| v.trim().to_owned())
}

/// The run's CPUs: `--cpus`, each checked to be in the launcher's own CPU set, or that set.
pub fn run_topology(cpus: Option<&str>) -> Result<Topology, UsageError> {
    let t = Topology::this_process();
    let Some(list) = cpus else { return Ok(t) };
    let wanted = parse_list(list, "--cpus")?;
    if let Some(c) = wanted.iter().find(|c| !t.allowed.contains(c)) {
        return Err(UsageError(format!(
            "--cpus `{list}` is not allowed: CPU {c} is not in this process's CPU set ({})",
            format_list(&t.allowed)
        )));
    }
    Ok(t.within(&wanted))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A machine of `physical` cores with `smt` hyperthreads each, numbered as Linux does
    /// on x86 (CPU `i` and `i + physical` are siblings), `isolated` of them isolated.
    fn machine(physical: usize, smt: usize, isolated: &[usize]) -> Topology {
        let allowed: Vec<usize> = (0..physical * smt).collect();
        let siblings = match smt {
            1 => Vec::new(),
            _ => (0..physical).map(|i| (0..smt).map(|t| i + t * physical).collect()).collect(),
        };
        Topology { allowed, isolated: isolated.to_vec(), siblings }
    }

    fn sibling_of(t: &Topology, a: usize, b: usize) -> bool {
        a == b || t.siblings.iter().any(|s| s.contains(&a) && s.contains(&b))
    }

    /// While the cores suffice, no core (and, while the physical cores suffice, no
    /// physical core) carries roles of two loops, every core is the process's, and the
    /// isolated cores are taken first.
    fn check_disjoint(t: &Topology, n: usize, shape: Shape) {
        let p = place(t, n, shape);
        let physical = t.cores().len();
        let threads = t.allowed.len();
        let need = n * shape.per_loop(threads, n);
        assert_eq!(p.loops.len(), n);
        assert_eq!(p.shared, need > threads, "{n} × {shape:?} on {threads}: {p:?}");
        for (i, a) in p.loops.iter().enumerate() {
            assert!(a.cpus.iter().all(|c| t.allowed.contains(c)), "{a:?} outside {t:?}");
            if let Some(roles) = a.roles {
                assert!(roles.iter().all(|r| a.cpus.contains(r)), "{a:?}");
            }
            for b in &p.loops[i + 1..] {
                for x in &a.cpus {
                    for y in &b.cpus {
                        if need <= physical {
                            assert!(!sibling_of(t, *x, *y), "{n} loops: {x} and {y}: {p:?}");
                        } else if need <= threads {
                            assert_ne!(x, y, "{n} loops: {p:?}");
                        }
                    }
                }
            }
        }
        let used: Vec<usize> = p.loops.iter().flat_map(|l| l.cpus.clone()).collect();
        let isolated = t.cores().iter().filter(|k| t.isolated.contains(&k[0])).count();
        if need <= isolated {
            assert!(used.iter().all(|c| t.isolated.contains(c)), "isolated first: {p:?}");
        }
        if need < physical {
            assert!(!used.contains(&0), "CPU 0 is the last one handed out: {p:?}");
        }
        if p.shared {
            assert!(p.notes.iter().any(|n| n.starts_with("cores shared")), "{p:?}");
        }
        if threads > physical {
            assert!(p.notes.iter().any(|n| n.starts_with("SMT")), "SMT is named: {p:?}");
        }
    }

    /// Synthetic 2-, 4-, 16- and 64-CPU machines, with and without SMT and isolated cores:
    /// every loop count from 1 to past the machine's cores, in every shape.
    #[test]
    fn loops_get_disjoint_cores_while_there_are_enough() {
        let machines = [
            machine(2, 1, &[]),
            machine(2, 2, &[]),
            machine(4, 1, &[2, 3]),
            machine(8, 2, &[]),
            machine(16, 1, &[8, 9, 10, 11, 12, 13, 14, 15]),
            machine(32, 2, &[16, 17, 18, 19, 48, 49, 50, 51]),
        ];
        for t in &machines {
            for shape in [Shape::SameCore, Shape::CrossCore, Shape::Dedicated, Shape::Unpinned] {
                for n in 1..=(t.allowed.len() + 3) {
                    check_disjoint(t, n, shape);
                }
            }
        }
    }

    /// The 16-core machine: 8 event loops on 2 cores each and 4 dedicated loops on
    /// 4 cores each, none sharing a core; 8 dedicated loops share, and say so.
    #[test]
    fn sixteen_cores_hold_eight_cross_core_or_four_dedicated_loops_apart() {
        let t = machine(16, 1, &[]);
        let cross = place(&t, 8, Shape::CrossCore);
        assert!(!cross.shared && cross.notes.is_empty(), "{cross:?}");
        let all: Vec<usize> = cross.loops.iter().flat_map(|l| l.cpus.clone()).collect();
        assert_eq!(all.len(), 16);
        let dedicated = place(&t, 4, Shape::Dedicated);
        assert!(!dedicated.shared);
        assert_eq!(
            dedicated.loops[0].pin().as_deref(),
            Some("plant=1,controller=2,reference=3,monitor=4")
        );
        let over = place(&t, 8, Shape::Dedicated);
        assert!(over.shared);
        assert!(over.notes[0].contains("CPU 1: 2"), "{:?}", over.notes);
    }

    /// A CPU set that is not 0…n−1 (`taskset -c 4-7`, a cgroup's cpuset): only its CPUs.
    #[test]
    fn only_the_process_cpu_set_is_used() {
        let t = machine(8, 1, &[]).within(&[4, 5, 6, 7]);
        let p = place(&t, 2, Shape::CrossCore);
        assert_eq!(p.loops[0].cpus, vec![4, 5]);
        assert_eq!(p.loops[1].cpus, vec![6, 7]);
        assert_eq!(p.loops[0].pin().as_deref(), Some("plant=4,controller=5,reference=5,monitor=4"));
    }

    /// Two physical cores with two hyperthreads each (CPUs 0/2 and 1/3): one cross-core
    /// loop takes one hyperthread of each; two loops take a physical core each, both its
    /// hyperthreads.
    #[test]
    fn smt_siblings_idle_while_physical_cores_suffice() {
        let t = machine(2, 2, &[]);
        let one = place(&t, 1, Shape::CrossCore);
        assert_eq!(one.loops[0].cpus, vec![0, 1]);
        assert!(one.notes[0].contains("left idle"), "{one:?}");
        let two = place(&t, 2, Shape::CrossCore);
        assert_eq!(two.loops[0].cpus, vec![1, 3]);
        assert_eq!(two.loops[1].cpus, vec![0, 2]);
        assert!(two.notes[0].contains("sibling hyperthreads used"), "{two:?}");
    }

    /// `--smt use` on 2 physical cores of 2 hyperthreads: two cross-core loops apart at
    /// once, each on both hyperthreads of one physical core, and said.
    #[test]
    fn smt_use_gives_each_loop_both_hyperthreads_of_its_cores() {
        let t = machine(2, 2, &[]);
        let one = place_smt(&t, 1, Shape::CrossCore, Smt::Use);
        assert_eq!(one.loops[0].cpus, vec![1, 3], "{one:?}");
        assert!(one.notes[0].contains("--smt use"), "{one:?}");
        let two = place_smt(&t, 2, Shape::CrossCore, Smt::Use);
        assert!(!two.shared);
        assert_eq!(two.loops[1].cpus, vec![0, 2]);
        // Without SMT the choice changes nothing.
        let flat = machine(4, 1, &[]);
        assert_eq!(
            place_smt(&flat, 2, Shape::CrossCore, Smt::Use),
            place(&flat, 2, Shape::CrossCore)
        );
    }

    #[test]
    fn cpu_lists_read_and_write_as_the_kernel_does() {
        assert_eq!(
            parse_list("0-3,8,10-11\n", "--cpus").expect("a list"),
            vec![0, 1, 2, 3, 8, 10, 11]
        );
        assert_eq!(format_list(&[0, 1, 2, 3, 8, 10, 11]), "0-3,8,10-11");
        assert_eq!(format_list(&[]), "-");
        for bad in ["", "a", "3-1", "0,,1", "-1", "4096", "1-"] {
            let e = parse_list(bad, "--cpus").expect_err(bad).0;
            assert!(e.starts_with("--cpus `") && e.contains("is not allowed"), "{bad}: {e}");
        }
    }

    /// The siblings and isolated CPUs of a fixture of `/sys` (this machine's files' form).
    #[test]
    fn topology_is_read_from_sysfs() {
        let dir = std::env::temp_dir().join(format!("rotorloop-cpus-{}", std::process::id()));
        let cpu = dir.join("devices/system/cpu");
        for (c, s) in [(0, "0,2"), (1, "1,3"), (2, "0,2"), (3, "1,3")] {
            let d = cpu.join(format!("cpu{c}/topology"));
            std::fs::create_dir_all(&d).expect("dir");
            std::fs::write(d.join("thread_siblings_list"), format!("{s}\n")).expect("write");
        }
        std::fs::write(cpu.join("isolated"), "1,3\n").expect("write");
        let t = Topology::read(&dir, vec![0, 1, 2, 3]);
        std::fs::remove_dir_all(&dir).expect("clean up");
        assert_eq!(t.isolated, vec![1, 3]);
        assert_eq!(t.siblings, vec![vec![0, 2], vec![1, 3]]);
        assert_eq!(place(&t, 1, Shape::SameCore).loops[0].cpus, vec![1]);
    }
}
