//! A command's error, typed until the edge words it: the terminal's `error: ...` line reads the
//! variant, so the field the user typed, the file a plan came from and the error of the layer
//! below stay data and are not parsed back out of text. (The Python package words it by its
//! text.)

use super::text::{compact, tidy};
use polar_engine::forecast::ForecastError;
use polar_engine::plan::PlanError;
use polar_engine::run::RunError;
use polar_model::ModelError;
use std::path::PathBuf;

/// An error of a layer below the command (the engine, the planner, a rig, a device, a file
/// format), kept with its type.
pub type LayerError = Box<dyn std::error::Error + Send + Sync + 'static>;

/// Why a command refused its input or could not finish. Each variant's text is the message the
/// user reads after `error: `; an input error's `field` lets the edge spell it as the flag the
/// user typed (`theta_i_deg` as `--theta-i-deg`).
#[derive(Debug, thiserror::Error)]
pub enum CommandError {
    /// A value the user gave is refused. `field` is the flag (`--sets`) or the key of a batch
    /// line, plan or file (`theta_i_deg`, `simulation.width`); `problem` follows it and names
    /// the value and what is allowed (` = 95 is out of range: allowed [0, 90]`).
    #[error("{field}{problem}")]
    Input {
        /// The flag or key, as the command knows it.
        field: String,
        /// What follows the field: the value and what is allowed.
        problem: String,
    },
    /// A plan is refused; `file` is the plan's file once the command knows it.
    #[error("{}", plan_message(file.as_ref(), source))]
    Plan {
        /// The plan's file.
        file: Option<PathBuf>,
        /// The plan's error: the field, the value and what is allowed.
        source: PlanError,
    },
    /// A file or folder the command reads or writes; `what` names it and what was being
    /// done (`--camera cam.toml: cannot read`).
    #[error("{what}: {source}")]
    File {
        /// The file, and what the command was doing with it.
        what: String,
        /// The system's error.
        source: std::io::Error,
    },
    /// A layer below failed; `context` (possibly empty) says what the command was doing.
    #[error("{context}{source}")]
    Layer {
        /// What the command was doing, ending in `: ` when not empty.
        context: String,
        /// The layer's own error.
        source: LayerError,
    },
    /// The command could not do what was asked (a run aborted, a target not in a layout).
    #[error("{0}")]
    Failed(String),
}

impl CommandError {
    /// A value the user gave refused: the field, then the problem (starting with its
    /// separator: ` = 3 is out of range: allowed ...`, `: ...`, ` has 2 values: ...`).
    pub fn input(field: impl Into<String>, problem: impl Into<String>) -> Self {
        CommandError::Input {
            field: field.into(),
            problem: problem.into(),
        }
    }

    /// A value outside its allowed range: `FIELD = VALUE is out of range: allowed ALLOWED`.
    pub fn out_of_range(
        field: impl Into<String>,
        value: impl std::fmt::Display,
        allowed: impl std::fmt::Display,
    ) -> Self {
        Self::input(
            field,
            format!(" = {value} is out of range: allowed {allowed}"),
        )
    }

    /// A file the command could not use: `WHAT: SYSTEM ERROR`.
    pub fn file(what: impl Into<String>, source: std::io::Error) -> Self {
        CommandError::File {
            what: what.into(),
            source,
        }
    }

    /// A layer's error with what the command was doing (`context`, ending in `: `, or empty).
    pub fn layer(
        context: impl Into<String>,
        source: impl std::error::Error + Send + Sync + 'static,
    ) -> Self {
        CommandError::Layer {
            context: context.into(),
            source: Box::new(source),
        }
    }

    /// A layer's error as it is; a plan's error (also inside a run's or a forecast's) becomes
    /// [`CommandError::Plan`] and a model's range error [`CommandError::Input`], so the edge
    /// can name the plan's file and the flag.
    pub fn of(source: impl std::error::Error + Send + Sync + 'static) -> Self {
        let source: LayerError = Box::new(source);
        let source = match source.downcast::<PlanError>() {
            Ok(plan) => return CommandError::from(*plan),
            Err(other) => other,
        };
        let source = match source.downcast::<ModelError>() {
            Ok(model) => return CommandError::from(*model),
            Err(other) => other,
        };
        let source = match source.downcast::<RunError>() {
            Ok(run) => match *run {
                RunError::Plan(plan) => return CommandError::from(plan),
                run => Box::new(run) as LayerError,
            },
            Err(other) => other,
        };
        let source = match source.downcast::<ForecastError>() {
            Ok(forecast) => match *forecast {
                ForecastError::Plan(plan) => return CommandError::from(plan),
                forecast => Box::new(forecast) as LayerError,
            },
            Err(other) => other,
        };
        CommandError::Layer {
            context: String::new(),
            source,
        }
    }

    /// A failure in words.
    pub fn failed(message: impl Into<String>) -> Self {
        CommandError::Failed(message.into())
    }

    /// The error with the plan's file named, when it is a plan's error (`plan FILE: FIELD =
    /// ...`); any other error as it is.
    pub fn in_plan_file(self, plan: &std::path::Path) -> Self {
        match self {
            CommandError::Plan { file: None, source } => CommandError::Plan {
                file: Some(plan.to_path_buf()),
                source,
            },
            other => other,
        }
    }
}

/// A plan's error, naming its file when known: `plan FILE: FIELD = VALUE is out of range:
/// allowed ...` (`plan FIELD ...` without the file).
fn plan_message(file: Option<&PathBuf>, e: &PlanError) -> String {
    let Some(file) = file else {
        return e.to_string();
    };
    match e {
        PlanError::Parse { path, message } => {
            format!("plan {}: {path}: {message}", file.display())
        }
        PlanError::Invalid {
            field,
            value,
            allowed,
        } => format!(
            "plan {}: {field} = {value} is out of range: allowed {allowed}",
            file.display()
        ),
        PlanError::Io { .. } => e.to_string(),
    }
}

impl From<ModelError> for CommandError {
    fn from(e: ModelError) -> Self {
        match e {
            ModelError::OutOfRange {
                field,
                value,
                allowed,
            } => Self::out_of_range(field, compact(value), allowed),
            ModelError::Invalid { field, reason } => {
                Self::input(field, format!(" is invalid: {}", tidy(&reason)))
            }
        }
    }
}

impl From<PlanError> for CommandError {
    fn from(source: PlanError) -> Self {
        CommandError::Plan { file: None, source }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A plan's range error reads `plan FILE: FIELD = VALUE ...` once the file is known, and
    /// `plan field FIELD = ...` before; the typed field survives for the edge.
    #[test]
    fn a_plan_error_names_its_file_once_known() {
        let e = CommandError::from(PlanError::Invalid {
            field: "capture.repeats".into(),
            value: "-1".into(),
            allowed: "1..=10000".into(),
        });
        assert_eq!(
            e.to_string(),
            "plan field capture.repeats = -1 is out of range: allowed 1..=10000"
        );
        let e = e.in_plan_file(std::path::Path::new("p.toml"));
        assert_eq!(
            e.to_string(),
            "plan p.toml: capture.repeats = -1 is out of range: allowed 1..=10000"
        );
        assert!(matches!(e, CommandError::Plan { .. }));
    }

    /// A model range error keeps its field as data and prints as before.
    #[test]
    fn a_model_range_error_is_an_input_error_with_its_field() {
        let e = CommandError::from(ModelError::OutOfRange {
            field: "theta_i_deg",
            value: 95.0,
            allowed: "[0, 90]",
        });
        assert!(matches!(&e, CommandError::Input { field, .. } if field == "theta_i_deg"));
        assert_eq!(
            e.to_string(),
            "theta_i_deg = 95 is out of range: allowed [0, 90]"
        );
    }

    /// A plan's error inside a run's error is still a plan's error, and names the file.
    #[test]
    fn a_plan_error_inside_a_run_error_is_found() {
        let e = CommandError::of(RunError::Plan(PlanError::Parse {
            path: "capture".into(),
            message: "missing field `angles_deg`".into(),
        }));
        let e = e.in_plan_file(std::path::Path::new("p.toml"));
        assert_eq!(
            e.to_string(),
            "plan p.toml: capture: missing field `angles_deg`"
        );
    }

    /// A file error keeps the system's error as its source.
    #[test]
    fn a_file_error_keeps_its_source() {
        let e = CommandError::file(
            "--camera c.toml: cannot read",
            std::io::Error::from(std::io::ErrorKind::NotFound),
        );
        assert!(std::error::Error::source(&e).is_some());
        assert!(matches!(e, CommandError::File { .. }));
        assert!(e.to_string().starts_with("--camera c.toml: cannot read: "));
    }
}
