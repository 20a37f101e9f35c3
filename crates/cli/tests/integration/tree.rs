//! The command tree: the root's help lists the groups of the tree and nothing else, each group
//! lists its subcommands, and the names of the flat tree resolve to the same commands (same
//! flags, same errors) while staying out of the help.

use std::process::{Command, Output};

const BIN: &str = env!("CARGO_BIN_EXE_polarimeter");

fn polarimeter(args: &[&str]) -> Output {
    Command::new(BIN)
        .args(args)
        .output()
        .expect("run polarimeter")
}

/// The names under `Commands:` of a help text.
fn commands(help: &str) -> Vec<String> {
    help.lines()
        .skip_while(|l| !l.starts_with("Commands:"))
        .skip(1)
        .take_while(|l| !l.trim().is_empty())
        .filter(|l| l.starts_with("  ") && !l.starts_with("   "))
        .filter_map(|l| l.split_whitespace().next().map(str::to_string))
        .collect()
}

/// The help of a command line (`... --help`), checked to exit 0.
fn help(args: &[&str]) -> String {
    let mut all = args.to_vec();
    all.push("--help");
    let out = polarimeter(&all);
    assert_eq!(
        out.status.code(),
        Some(0),
        "{all:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).expect("utf-8 help")
}

/// A help text's options and subcommands: everything after its `Usage:` line, with the
/// command's path taken out.
fn body(help: &str) -> String {
    help.lines()
        .skip_while(|l| !l.starts_with("Usage:"))
        .skip(1)
        .filter(|l| !l.trim_start().starts_with("polarimeter "))
        .collect::<Vec<_>>()
        .join("\n")
}

#[test]
fn root_help_lists_only_the_groups() {
    assert_eq!(
        commands(&help(&[])),
        [
            "model",
            "plan",
            "acquire",
            "demo",
            "devices",
            "simulate",
            "analyze",
            "calibrate",
            "report",
            "bench",
            "station",
            "help"
        ]
    );
}

#[test]
fn every_group_lists_its_subcommands() {
    let groups: [(&[&str], &[&str]); 12] = [
        (
            &["plan"],
            &["scene", "angles", "check", "continuous", "schema"],
        ),
        (
            &["station"],
            &[
                "serve", "key", "status", "health", "submit", "validate", "queue", "remove",
                "move", "start", "stop", "pause", "resume", "abort", "history",
            ],
        ),
        (&["station", "key"], &["create", "revoke", "list"]),
        (&["acquire"], &["run", "resume", "check", "demo", "export"]),
        (&["acquire", "export"], &["tiff"]),
        (&["devices"], &["list", "stage", "camera"]),
        (
            &["devices", "stage"],
            &["info", "home", "move", "slot", "position"],
        ),
        (&["devices", "camera"], &["grab"]),
        (&["simulate"], &["stage", "photon-transfer"]),
        (&["analyze"], &["aptd"]),
        (&["calibrate"], &["noise"]),
        (&["report"], &["figures", "validation", "study"]),
    ];
    for (group, subcommands) in groups {
        let mut expected: Vec<&str> = subcommands.to_vec();
        expected.push("help");
        assert_eq!(commands(&help(group)), expected, "{group:?}");
    }
    assert_eq!(
        commands(&help(&["bench"])),
        ["run", "scene", "stats", "planner", "serial", "faults", "crash", "help"]
    );
}

#[test]
fn the_flat_tree_names_resolve_to_the_same_commands() {
    let pairs: [(&[&str], &[&str]); 12] = [
        (&["run"], &["acquire", "run"]),
        (&["resume"], &["acquire", "resume"]),
        (&["check"], &["acquire", "check"]),
        (&["export", "tiff"], &["acquire", "export", "tiff"]),
        (&["stage"], &["devices", "stage"]),
        (&["stage", "move"], &["devices", "stage", "move"]),
        (&["camera"], &["devices", "camera"]),
        (&["camera", "grab"], &["devices", "camera", "grab"]),
        (&["sim", "stage"], &["simulate", "stage"]),
        (&["sim", "frames"], &["simulate", "photon-transfer"]),
        (&["study"], &["report", "study"]),
        (&["plan", "aptd"], &["analyze", "aptd"]),
    ];
    for (old, new) in pairs {
        let (old_help, new_help) = (help(old), help(new));
        assert!(old_help.contains("Options:"), "{old:?}: {old_help}");
        assert_eq!(body(&old_help), body(&new_help), "{old:?} against {new:?}");
    }
    assert_eq!(body(&help(&["demo"])), body(&help(&["acquire", "demo"])));
}

#[test]
fn plan_with_scene_flags_is_plan_scene() {
    let flags = [
        "--scene",
        "../../examples/rooftop.toml",
        "--camera",
        "../../examples/cameras/cmos_modern.toml",
        "--target",
        "panel",
        "--background",
        "asphalt",
        "--channels",
        "9",
    ];
    let old = polarimeter(&[&["plan"][..], &flags].concat());
    let new = polarimeter(&[&["plan", "scene"][..], &flags].concat());
    assert_eq!(old.status.code(), Some(2));
    assert_eq!(new.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&new.stderr);
    assert!(stderr.contains("--channels"), "{stderr}");
    assert_eq!(old.stderr, new.stderr);
}

/// A mistyped subcommand or flag is refused (exit status 2) on one line that names clap's
/// suggestion, so a user can guess their way: `plan secne` suggests `scene`, `model fresnel
/// --theta-i 60` suggests `--theta-i-deg`.
#[test]
fn mistypes_suggest_the_name_meant() {
    for (args, meant) in [
        (&["plan", "secne"][..], "`scene`"),
        (&["acquire", "resum", "x"][..], "`resume`"),
        (
            &["model", "fresnel", "--n", "1.5", "--theta-i", "60"][..],
            "`--theta-i-deg`",
        ),
    ] {
        let out = polarimeter(args);
        assert_eq!(out.status.code(), Some(2), "{args:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(err.trim().lines().count(), 1, "{args:?}: {err}");
        assert!(
            err.contains(&format!("did you mean {meant}?")),
            "{args:?}: {err}"
        );
    }
}
