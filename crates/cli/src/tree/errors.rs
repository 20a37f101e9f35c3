//! Errors as the user sees them: clap's parse errors on one line naming the flag, the value and
//! what is allowed; a command's error naming the flag the user typed; the command line with the
//! flat tree's `plan --scene ...` spelled as `plan scene --scene ...`.

use clap::error::{ContextKind, ContextValue, ErrorKind};
use polar_cli::{batch, commands};
use std::ffi::OsString;

/// The command line to parse: the program's arguments, with `plan` followed by a flag of
/// `plan scene` (`plan --scene FILE ...`) read as `plan scene ...`.
pub fn argv() -> Vec<OsString> {
    let mut args: Vec<OsString> = std::env::args_os().collect();
    let plan = args.iter().position(|a| a == "plan");
    let before_plan_are_flags = plan.is_some_and(|p| {
        args[1..p]
            .iter()
            .all(|a| a.to_str().is_some_and(|s| s.starts_with('-')))
    });
    if let (Some(p), true) = (plan, before_plan_are_flags) {
        let next = args.get(p + 1).and_then(|a| a.to_str());
        if next.is_some_and(|n| n.starts_with("--") && n != "--help" && n != "--version") {
            args.insert(p + 1, OsString::from("scene"));
        }
    }
    args
}

/// A clap parse error as one line naming the flag, the value (cut when long) and what is
/// allowed, with clap's suggestion when the user mistyped a subcommand or a flag ("did you
/// mean `scene`?").
pub fn one_line_error(e: &clap::Error) -> String {
    let line = error_line(e);
    let suggested = [ContextKind::SuggestedSubcommand, ContextKind::SuggestedArg]
        .into_iter()
        .find_map(|k| match e.get(k) {
            Some(ContextValue::String(s)) => Some(s.clone()),
            Some(ContextValue::Strings(v)) if !v.is_empty() => Some(v.join("` or `")),
            _ => None,
        });
    match suggested {
        Some(s) => format!("{line}; did you mean `{s}`?"),
        None => line,
    }
}

fn error_line(e: &clap::Error) -> String {
    let arg = match e.get(ContextKind::InvalidArg) {
        Some(ContextValue::String(s)) => s.clone(),
        _ => String::new(),
    };
    let value = match e.get(ContextKind::InvalidValue) {
        Some(ContextValue::String(s)) => s.clone(),
        _ => String::new(),
    };
    if e.kind() == ErrorKind::ArgumentConflict {
        let mut flags: Vec<String> = match e.get(ContextKind::PriorArg) {
            Some(ContextValue::String(s)) => vec![s.clone()],
            Some(ContextValue::Strings(v)) => v.clone(),
            _ => Vec::new(),
        };
        flags.insert(0, arg.clone());
        let flags: Vec<String> = flags
            .iter()
            .map(|f| f.split([' ', '=']).next().unwrap_or(f).to_string())
            .collect();
        if flags.iter().any(|f| f == "--batch") {
            let others: Vec<&str> = flags
                .iter()
                .filter(|f| *f != "--batch")
                .map(String::as_str)
                .collect();
            return format!(
                "error: --batch cannot be used with {}: each batch line gives its own values \
                 (allowed: --batch FILE alone, or the flags without --batch)",
                others.join(", ")
            );
        }
        return format!(
            "error: {} cannot be used with {} (see --help)",
            flags[0],
            flags[1..].join(", ")
        );
    }
    let field = arg
        .trim_start_matches('-')
        .split([' ', '<', '='])
        .next()
        .unwrap_or("")
        .replace('-', "_");
    let mut first = e
        .to_string()
        .lines()
        .next()
        .unwrap_or("invalid arguments")
        .to_string();
    let n = value.chars().count();
    if n > commands::ECHO_MAX {
        let head: String = value.chars().take(commands::ECHO_MAX).collect();
        first = first.replacen(&value, &format!("{head}… ({n} characters)"), 1);
    }
    match (batch::allowed(&field), value.is_empty()) {
        (Some(allowed), false) => format!(
            "error: {arg} = {} is invalid: allowed {allowed}",
            commands::echo(&value)
        ),
        (Some(allowed), true) => format!("{first}; allowed {allowed}"),
        (None, _) => match e.get(ContextKind::ValidValue) {
            // A flag with a fixed list of values (`demo --stage`): name them.
            Some(ContextValue::Strings(valid)) if !valid.is_empty() => {
                format!("{first}: allowed one of {}", valid.join(", "))
            }
            _ => format!("{first} (see --help)"),
        },
    }
}

/// The long flags of the subcommand the command line names (`model fresnel`: `n`, `k`,
/// `theta-i-deg`, `batch`).
fn command_flags() -> Vec<String> {
    use clap::CommandFactory;
    let mut cmd = crate::Cli::command();
    cmd.build();
    let mut current = &cmd;
    for arg in argv().into_iter().skip(1) {
        if let Some(sub) = arg.to_str().and_then(|a| current.find_subcommand(a)) {
            current = sub;
        }
    }
    current
        .get_arguments()
        .filter_map(|a| a.get_long().map(str::to_string))
        .collect()
}

/// A command's error as the user sees it: an input error's field that is one of the command's
/// flags spelled as the flag (`theta_i_deg = 95` -> `--theta-i-deg = 95`), long echoed text cut
/// and long numbers compact.
pub fn user_error(e: &commands::CommandError) -> String {
    use commands::CommandError;
    match e {
        CommandError::Input { field, problem } => {
            let flag = field.replace('_', "-");
            if !field.starts_with('-') && command_flags().contains(&flag) {
                commands::tidy(&format!("--{flag}{problem}"))
            } else {
                commands::tidy(&e.to_string())
            }
        }
        // Another layer's error is worded by its text, as the layers' own error types are.
        CommandError::Layer { .. } => message_error(&e.to_string()),
        _ => commands::tidy(&e.to_string()),
    }
}

/// An error of another layer's type as the user sees it: long echoed text cut and long
/// numbers compact, and a leading field that is one of the command's flags spelled as the
/// flag, for the errors whose text starts with the field they name (a device's angle).
pub fn message_error(message: &str) -> String {
    let message = commands::tidy(message);
    let end = message
        .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
        .unwrap_or(message.len());
    let (token, rest) = message.split_at(end);
    let named = [" = ", " is ", " has ", " contains ", ": ", "["]
        .iter()
        .any(|p| rest.starts_with(p));
    let flag = token.replace('_', "-");
    if !token.is_empty() && named && command_flags().contains(&flag) {
        format!("--{flag}{rest}")
    } else {
        message
    }
}

/// An error as the terminal words it after `error: `.
pub trait Worded {
    /// The message.
    fn worded(&self) -> String;
}

impl Worded for commands::CommandError {
    fn worded(&self) -> String {
        user_error(self)
    }
}

/// Errors of the layers whose text is the message ([`message_error`]).
macro_rules! worded_by_text {
    ($($t:ty),* $(,)?) => {
        $(impl Worded for $t {
            fn worded(&self) -> String {
                message_error(&self.to_string())
            }
        })*
    };
}

worded_by_text!(
    polar_cli::calibrate::CalibrateError,
    polar_cli::devices::DevicesError,
    polar_cli::study::StudyError,
    polar_station::StationError,
);
