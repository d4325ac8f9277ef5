//! The commands of `emr-edge`, one module each, and the argument groups they share.

pub mod convert;
pub mod eval;
pub mod odometry;
pub mod posegraph;
pub mod run;
pub mod sim;

pub use edge::args::{SourceArgs, TuningArgs};
use indicatif::{ProgressBar, ProgressStyle};

/// A progress bar on stderr; indicatif draws nothing when stderr is not a terminal.
fn progress_bar(len: Option<usize>, unit: &str) -> ProgressBar {
    let bar = len.map_or_else(ProgressBar::new_spinner, |n| ProgressBar::new(n as u64));
    let template = if len.is_some() {
        format!("{{bar:40}} {{pos}}/{{len}} {unit} [{{elapsed}} < {{eta}}, {{per_sec}}]")
    } else {
        format!("{{spinner}} {{pos}} {unit} [{{elapsed}}, {{per_sec}}]")
    };
    if let Ok(style) = ProgressStyle::with_template(&template) {
        bar.set_style(style);
    }
    bar
}
