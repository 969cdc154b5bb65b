//! The README's commands work as written. A fresh clone once failed at the README's first
//! command ("`cargo run` could not determine which binary to run") while every test
//! passed; these tests read the commands from `README.md` itself, never from a copy:
//!
//! - the two set-up commands (the first code block under "Two commands") resolve and
//!   start exactly as written (`--help` appended to the program's arguments, or `--list`
//!   to the test harness's, so nothing long runs), and `.ci/run` calls the test command;
//! - every other `rotorloop …` command line in the README and in `docs/*.md` (code blocks
//!   and inline code) names a subcommand that exists and only flags that subcommand
//!   accepts; the ones in code blocks, which are meant to be pasted, also parse with
//!   their values;
//! - the README is a front page (at most 200 lines) whose links to `docs/` all resolve,
//!   and every page in `docs/` is linked from it.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn readme() -> String {
    std::fs::read_to_string(root().join("README.md")).expect("README.md")
}

/// The commands of the first fenced block after the `## Two commands` heading, one per
/// line, without their `# …` comments.
fn setup_commands(readme: &str) -> Vec<String> {
    let section = readme.split("\n## Two commands").nth(1).expect("a `## Two commands` section");
    let block = section.split("```").nth(1).expect("a code block in `## Two commands`");
    block
        .lines()
        .skip(1) // the fence's language tag
        .map(|l| l.split(" #").next().unwrap_or("").trim().to_owned())
        .filter(|l| !l.is_empty())
        .collect()
}

/// Command lines in fenced code blocks (continuation lines joined), and inline code spans
/// that start with `rotorloop `. Returns (command, from a code block).
fn command_lines(readme: &str) -> Vec<(String, bool)> {
    let mut out = Vec::new();
    for (i, part) in readme.split("```").enumerate() {
        if i % 2 == 1 {
            let joined = part.replace("\\\n", " ");
            for line in joined.lines().skip(1) {
                let line = line.trim();
                if line.starts_with("rotorloop ") || line.starts_with("cargo run ") {
                    out.push((line.split(" #").next().unwrap_or(line).trim().to_owned(), true));
                }
            }
        } else {
            // Inline spans: split on backticks, odd pieces are code. A table cell escapes
            // `|` as `\|`.
            for (j, span) in part.split('`').enumerate() {
                if j % 2 == 1 && span.starts_with("rotorloop ") {
                    out.push((span.replace("\\|", "|"), false));
                }
            }
        }
    }
    // `rotorloop (root package)` in a tree, `rotorloop role <name>` in prose: not command
    // lines. A command names its subcommands in plain words.
    out.retain(|(line, _)| {
        let (sub, _) = split_command(line);
        !sub.is_empty()
            && sub.iter().all(|w| w.bytes().all(|b| b.is_ascii_lowercase() || b == b'-'))
    });
    out
}

/// The `rotorloop` subcommand path of a command line and the arguments after it.
fn split_command(line: &str) -> (Vec<String>, Vec<String>) {
    // As a shell splits it: quotes group words (`--controller-cmd "python3 c.py"`).
    let words = rotorloop::run::external::split_words(line)
        .unwrap_or_else(|_| line.split_whitespace().map(str::to_owned).collect());
    let args: Vec<String> = if words[0] == "cargo" {
        let dd = words.iter().position(|w| w == "--").expect("`cargo run … -- ARGS`");
        words[dd + 1..].to_vec()
    } else {
        words[1..].to_vec()
    };
    let depth = if args.first().is_some_and(|a| a == "role") { 2 } else { 1 };
    let depth = depth.min(args.len());
    (args[..depth].to_vec(), args[depth..].to_vec())
}

/// The `--flags` a piece of text names (inside `[ … ]` too).
fn flags_in(text: &str) -> Vec<String> {
    let mut flags = Vec::new();
    let b = text.as_bytes();
    let mut i = 0;
    while i + 2 < b.len() {
        let starts = b[i] == b'-'
            && b[i + 1] == b'-'
            && (i == 0 || !b[i - 1].is_ascii_alphanumeric() && b[i - 1] != b'-');
        if starts && b[i + 2].is_ascii_lowercase() {
            let end = (i + 2..b.len())
                .find(|&j| !(b[j].is_ascii_lowercase() || b[j].is_ascii_digit() || b[j] == b'-'))
                .unwrap_or(b.len());
            flags.push(text[i..end].to_owned());
            i = end;
        } else {
            i += 1;
        }
    }
    flags
}

fn rotorloop(args: &[String]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_rotorloop")).args(args).output().expect("run rotorloop")
}

/// Cargo as a newcomer's shell runs it: without the variables cargo set for this test
/// process (`CARGO_MANIFEST_DIR`, `CARGO_PKG_NAME`, ...). Build scripts watch some of
/// them (`ring`'s `rerun-if-env-changed`), so with them set the nested cargo rebuilt
/// the whole Zenoh stack, and the next `cargo test` rebuilt it back (about 3 min each).
fn cargo() -> Command {
    let mut c = Command::new(std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into()));
    c.current_dir(root());
    const SET_BY_CARGO_FOR_TESTS: [&str; 6] = [
        "CARGO_PKG_",
        "CARGO_MANIFEST_",
        "CARGO_CRATE_",
        "CARGO_BIN_",
        "CARGO_PRIMARY_",
        "OUT_DIR",
    ];
    for (key, _) in std::env::vars_os() {
        let k = key.to_string_lossy();
        if SET_BY_CARGO_FOR_TESTS.iter().any(|p| k.starts_with(p)) || k == "CARGO_TARGET_TMPDIR" {
            c.env_remove(&key);
        }
    }
    c
}

fn text(o: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

/// The README's main command (`cargo run … -- ARGS`) resolves a binary and starts the
/// subcommand it names, exactly as written: cargo is run with the README's own cargo
/// arguments, and the program's arguments get `--help` appended (clap has then checked
/// every argument before it, names and values).
#[test]
fn readme_main_command_resolves_and_starts_as_written() {
    let cmds = setup_commands(&readme());
    let run =
        cmds.iter().find(|c| c.starts_with("cargo run")).expect("a `cargo run` set-up command");
    let words: Vec<&str> = run.split_whitespace().collect();
    let mut c = cargo();
    c.args(&words[1..]).arg("--help");
    let o = c.output().expect("run cargo");
    let (sub, _) = split_command(run);
    assert!(
        o.status.success(),
        "the README's main command `{run}` does not start (with --help appended):\n{}",
        text(&o)
    );
    let usage = format!("Usage: rotorloop {}", sub.join(" "));
    assert!(text(&o).contains(&usage), "`{run} --help` did not print `{usage}`:\n{}", text(&o));
}

/// The README's test command resolves and its harness starts (`-- --list`: every test
/// binary builds and lists its tests without running them), and `.ci/run` runs exactly it.
#[test]
fn readme_test_command_resolves_and_ci_runs_it() {
    let cmds = setup_commands(&readme());
    let test =
        cmds.iter().find(|c| c.starts_with("cargo test")).expect("a `cargo test` set-up command");
    let ci = std::fs::read_to_string(root().join(".ci/run")).expect(".ci/run");
    assert!(
        ci.lines().any(|l| l.trim() == test),
        "`.ci/run` does not run the README's test command `{test}` as a line of its own"
    );
    let words: Vec<&str> = test.split_whitespace().collect();
    let mut c = cargo();
    c.args(&words[1..]);
    if !words.contains(&"--") {
        c.arg("--");
    }
    let o = c.arg("--list").output().expect("run cargo");
    assert!(o.status.success(), "the README's test command `{test}` does not start:\n{}", text(&o));
    assert!(
        String::from_utf8_lossy(&o.stdout)
            .contains("readme_test_command_resolves_and_ci_runs_it: test"),
        "`{test} -- --list` did not list this very test:\n{}",
        text(&o)
    );
}

/// The guide's pages: `docs/*.md`, with their text.
fn docs_pages() -> Vec<(String, String)> {
    let mut pages: Vec<(String, String)> = std::fs::read_dir(root().join("docs"))
        .expect("docs/")
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "md"))
        .map(|p| {
            let name = format!("docs/{}", p.file_name().expect("a name").to_string_lossy());
            (name, std::fs::read_to_string(&p).expect("a page"))
        })
        .collect();
    pages.sort();
    pages
}

/// Every `rotorloop …` command line of the README and of the guide names an existing
/// subcommand and only flags it accepts; those in code blocks parse with their values as
/// written.
#[test]
fn every_command_line_of_the_readme_and_the_docs_parses() {
    let mut lines: Vec<(String, (String, bool))> =
        command_lines(&readme()).into_iter().map(|l| ("README.md".to_owned(), l)).collect();
    let in_readme = lines.len();
    for (page, text) in docs_pages() {
        lines.extend(command_lines(&text).into_iter().map(|l| (page.clone(), l)));
    }
    assert!(in_readme >= 3, "found only {in_readme} command lines in README.md");
    assert!(lines.len() > 40, "found only {} command lines in README.md and docs/", lines.len());
    let mut problems = Vec::new();
    for (page, (line, pasteable)) in &lines {
        let (sub, rest) = split_command(line);
        let mut help_args = sub.clone();
        help_args.push("--help".into());
        let o = rotorloop(&help_args);
        if !o.status.success() {
            problems
                .push(format!("{page}: `{line}`: `rotorloop {}` is not a command", sub.join(" ")));
            continue;
        }
        let help = String::from_utf8_lossy(&o.stdout).into_owned();
        let accepted = flags_in(&help);
        for flag in flags_in(&rest.join(" ")) {
            if !accepted.contains(&flag) {
                problems.push(format!(
                    "{page}: `{line}`: `rotorloop {}` has no flag `{flag}`",
                    sub.join(" ")
                ));
            }
        }
        if *pasteable {
            let mut args = sub.clone();
            args.extend(rest.iter().cloned());
            args.push("--help".into());
            let o = rotorloop(&args);
            if !o.status.success() {
                problems.push(format!("{page}: `{line}` does not parse: {}", text(&o).trim()));
            }
        }
    }
    assert!(problems.is_empty(), "command lines that do not work:\n{}", problems.join("\n"));
}

/// The README is a front page: at most 200 lines, its links into `docs/` resolve, and
/// every page of the guide is linked from it (a page nobody links is a page nobody reads).
#[test]
fn the_readme_is_a_front_page_that_links_every_page_of_the_guide() {
    let readme = readme();
    let lines = readme.lines().count();
    assert!(lines <= 200, "README.md has {lines} lines; the front page keeps to 200");
    let links: Vec<&str> = readme
        .split("](")
        .skip(1)
        .filter_map(|l| l.split(')').next())
        .filter(|l| l.starts_with("docs/"))
        .collect();
    for link in &links {
        assert!(root().join(link).exists(), "README.md links `{link}`, which does not exist");
    }
    let pages = docs_pages();
    assert!(pages.len() >= 9, "docs/ has only {} pages", pages.len());
    for (page, _) in &pages {
        assert!(links.contains(&page.as_str()), "README.md does not link {page}");
    }
}

/// The extraction itself: the set-up block is two commands, and a table cell's escaped
/// `\|` and an inline span's flags are read (so the tests above cannot pass by finding
/// nothing).
#[test]
fn readme_extraction_finds_what_it_should() {
    let md = "x\n## Two commands\n\n```sh\ncargo run --release -- paper --out o   # main\ncargo test --workspace   # tests\n```\n\
              | `rotorloop run --mode lockstep\\|realtime [--rate HZ]` | y |\n```sh\nrotorloop bench --rates 1 \\\n    --seconds 5 --out o\n```\n\
              `rotorloop role <name>` and\n```\nrotorloop (root package)\n```\n";
    assert_eq!(
        setup_commands(md),
        ["cargo run --release -- paper --out o", "cargo test --workspace"]
    );
    let lines = command_lines(md);
    assert_eq!(
        lines,
        [
            ("cargo run --release -- paper --out o".to_owned(), true),
            ("rotorloop run --mode lockstep|realtime [--rate HZ]".to_owned(), false),
            ("rotorloop bench --rates 1      --seconds 5 --out o".to_owned(), true)
        ]
    );
    assert_eq!(flags_in(&lines[1].0), ["--mode", "--rate"]);
    assert_eq!(split_command("cargo run --release -- paper --out o").0, ["paper"]);
    assert_eq!(split_command("rotorloop role probe --domain D").0, ["role", "probe"]);
    assert!(Path::new(&root().join("README.md")).exists());
}
