//! The kernel's scheduler trace of a `--trace-sched` run (`sched-trace.txt`, tracefs text
//! lines with the `mono` clock): who ran on a CPU instead of a late process, and the
//! IRQs it served.

use std::collections::BTreeMap;
use std::path::Path;

/// A task: its command name and pid.
pub type Task = (String, u32);

/// One event of the trace.
#[derive(Debug, Clone, PartialEq)]
pub enum Event {
    /// A CPU switched from one task to another.
    Switch {
        /// The task that ran until now.
        prev: (String, u32),
        /// The task that runs from now.
        next: (String, u32),
    },
    /// A task was woken.
    Wakeup(String, u32),
    /// An IRQ handler began.
    IrqEntry(u32, String),
    /// An IRQ handler ended.
    IrqExit(u32),
}

/// An event, when (monotonic ns) and on which CPU.
#[derive(Debug, Clone, PartialEq)]
pub struct Traced {
    /// When (ns of `CLOCK_MONOTONIC`).
    pub t_ns: u64,
    /// The CPU.
    pub cpu: u32,
    /// What.
    pub event: Event,
}

/// `key=value` of `body`, the value up to the next ` key2=` (a command name may hold
/// spaces).
fn field<'a>(body: &'a str, key: &str, next: Option<&str>) -> Option<&'a str> {
    let start = body.find(&format!("{key}="))? + key.len() + 1;
    let rest = &body[start..];
    let end = next
        .and_then(|n| rest.find(&format!(" {n}=")))
        .unwrap_or_else(|| rest.find(' ').unwrap_or(rest.len()));
    Some(&rest[..end])
}

/// One line of the trace, if it is an event this module reads.
pub fn parse(line: &str) -> Option<Traced> {
    let names = ["sched_switch", "sched_wakeup", "irq_handler_entry", "irq_handler_exit"];
    let (i, name) = names.iter().find_map(|n| line.find(&format!(": {n}: ")).map(|i| (i, *n)))?;
    let (head, body) = (&line[..i], &line[i + name.len() + 4..]);
    let mut words = head.split_whitespace().rev();
    let (secs, frac) = words.next()?.split_once('.')?;
    let frac_ns: u64 = format!("{frac:0<9}").get(..9)?.parse().ok()?;
    let t_ns = secs.parse::<u64>().ok()? * 1_000_000_000 + frac_ns;
    let cpu =
        words.find_map(|w| w.strip_prefix('[').and_then(|w| w.strip_suffix(']')))?.parse().ok()?;
    let num = |s: Option<&str>| s.and_then(|s| s.parse::<u32>().ok());
    let event = match name {
        "sched_switch" => Event::Switch {
            prev: (
                field(body, "prev_comm", Some("prev_pid"))?.to_owned(),
                num(field(body, "prev_pid", None))?,
            ),
            next: (
                field(body, "next_comm", Some("next_pid"))?.to_owned(),
                num(field(body, "next_pid", None))?,
            ),
        },
        "sched_wakeup" => Event::Wakeup(
            field(body, "comm", Some("pid"))?.to_owned(),
            num(field(body, " pid", None).or_else(|| field(body, "pid", None)))?,
        ),
        "irq_handler_entry" => {
            Event::IrqEntry(num(field(body, "irq", None))?, field(body, "name", None)?.to_owned())
        }
        _ => Event::IrqExit(num(field(body, "irq", None))?),
    };
    Some(Traced { t_ns, cpu, event })
}

/// The events of the trace at `path` in the file's order, read a line at a time (none
/// where it is missing; a line that is not an event is skipped). The file is in time order
/// but for events of one CPU committed late (per-CPU buffers), a few at most.
pub fn events(path: &Path) -> impl Iterator<Item = Traced> + use<> {
    use std::io::BufRead;
    let lines = std::fs::File::open(path).ok().map(|f| std::io::BufReader::new(f).lines());
    lines.into_iter().flatten().map_while(Result::ok).filter_map(|l| parse(&l))
}

/// What ran on `cpu` over `[from, to]` (ns): each task's time on it, and the IRQ
/// handlers' time.
pub fn occupancy(events: &[Traced], cpu: u32, [from, to]: [u64; 2]) -> (Vec<(Task, u64)>, u64) {
    let mut ran: BTreeMap<Task, u64> = BTreeMap::new();
    let mut current: Option<(Task, u64)> = None;
    let (mut irq_ns, mut irq_since) = (0u64, None::<u64>);
    let clip = |a: u64, b: u64| b.min(to).saturating_sub(a.max(from));
    for e in events.iter().filter(|e| e.cpu == cpu).take_while(|e| e.t_ns <= to) {
        match &e.event {
            Event::Switch { prev, next } => {
                let since = current.as_ref().map_or(e.t_ns, |c| c.1);
                *ran.entry(prev.clone()).or_default() += clip(since, e.t_ns);
                current = Some((next.clone(), e.t_ns));
            }
            Event::IrqEntry(..) => irq_since = Some(e.t_ns),
            Event::IrqExit(_) => {
                if let Some(s) = irq_since.take() {
                    irq_ns += clip(s, e.t_ns);
                }
            }
            Event::Wakeup(..) => {}
        }
    }
    if let Some((task, since)) = current {
        *ran.entry(task).or_default() += clip(since, to);
    }
    let mut v: Vec<(Task, u64)> = ran.into_iter().filter(|(_, ns)| *ns > 0).collect();
    v.sort_by_key(|(_, ns)| std::cmp::Reverse(*ns));
    (v, irq_ns)
}

#[cfg(test)]
mod tests {
    use super::*;

    const SWITCH: &str = "          <idle>-0       [001] d..2.  1234.567890: sched_switch: \
        prev_comm=swapper/1 prev_pid=0 prev_prio=120 prev_state=R ==> next_comm=my task \
        next_pid=5678 next_prio=49";

    #[test]
    fn trace_lines_are_read_with_their_time_cpu_and_tasks() {
        let e = parse(SWITCH).expect("a switch");
        assert_eq!((e.t_ns, e.cpu), (1_234_567_890_000, 1));
        let want = Event::Switch { prev: ("swapper/1".into(), 0), next: ("my task".into(), 5678) };
        assert_eq!(e.event, want);
        let w = parse(
            "  yes-9 [000] dN.1. 5.000001: sched_wakeup: comm=plant pid=42 prio=120 target_cpu=000",
        );
        assert_eq!(w.map(|w| w.event), Some(Event::Wakeup("plant".into(), 42)));
        let i = parse("  yes-9 [000] d.h1. 5.5: irq_handler_entry: irq=11 name=virtio0");
        assert_eq!(
            i.map(|i| (i.t_ns, i.event)),
            Some((5_500_000_000, Event::IrqEntry(11, "virtio0".into())))
        );
        assert_eq!(parse("# tracer: nop"), None);
    }

    #[test]
    fn occupancy_adds_each_tasks_time_within_the_window() {
        let sw = |t: u64, prev: u32, next: u32| Traced {
            t_ns: t,
            cpu: 1,
            event: Event::Switch {
                prev: (format!("p{prev}"), prev),
                next: (format!("p{next}"), next),
            },
        };
        let events = [sw(0, 0, 7), sw(100, 7, 9), sw(150, 9, 7)];
        let (ran, irq) = occupancy(&events, 1, [50, 200]);
        assert_eq!(ran, vec![(("p7".into(), 7), 100), (("p9".into(), 9), 50)]);
        assert_eq!(irq, 0);
    }

    #[test]
    fn the_events_are_read_in_the_files_order_skipping_what_is_not_one() {
        let dir = std::env::temp_dir().join(format!("rotorloop-trace-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("a temporary folder");
        let path = dir.join("sched-trace.txt");
        let line = |t: &str| SWITCH.replace("1234.567890", t);
        // Out of order across CPUs, as per-CPU buffers can be; a header line; a bad line.
        let text = ["# tracer: nop".to_owned(), line("7.0"), line("2.5"), line("3.0"), line("x")];
        std::fs::write(&path, text.join("\n")).expect("write");
        let t: Vec<u64> = events(&path).map(|e| e.t_ns).collect();
        assert_eq!(t, [7_000_000_000, 2_500_000_000, 3_000_000_000]);
        assert_eq!(events(&dir.join("none.txt")).count(), 0);
        std::fs::remove_dir_all(&dir).expect("remove");
    }
}
