//! The table `emr-eval robustness` prints: one row per case, ours beside KISS-ICP.

use std::fmt;

use super::run::{Outcome, Verdict};

/// One case's results.
#[derive(Clone, Debug, PartialEq)]
pub struct Row {
    /// Case name.
    pub name: String,
    /// Class of hard input.
    pub class: String,
    /// Scans in the case (0 when it could not be built).
    pub scans: usize,
    /// Our odometry.
    pub ours: Outcome,
    /// KISS-ICP, when it ran.
    pub kiss: Option<Outcome>,
}

impl Row {
    /// The true path length, from whichever verdict has it.
    pub fn path_m(&self) -> Option<f64> {
        let verdicts = std::iter::once(&self.ours).chain(&self.kiss);
        verdicts.filter_map(|o| o.verdict.as_ref().ok()).map(|v| v.path_m).next()
    }
}

/// The rows as a Markdown table.
pub struct Table<'a>(pub &'a [Row]);

const HEADER: &str = "| case | class | scans | path m | ours ATE m | ours held | lost | recoveries | KISS ATE m | \
                      KISS held | ours ms/scan | KISS ms/scan |\n|---|---|---|---|---|---|---|---|---|---|---|---|";

impl fmt::Display for Table<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "{HEADER}")?;
        for row in self.0 {
            let kiss = row.kiss.as_ref();
            let (kiss_ate, kiss_held) = kiss.map_or(("-".into(), "-".into()), |k| (ate(k), held(k)));
            writeln!(
                f,
                "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
                row.name,
                row.class,
                row.scans,
                row.path_m().map_or("-".into(), |p| format!("{p:.1}")),
                ate(&row.ours),
                held(&row.ours),
                count(row.ours.lost),
                count(row.ours.recoveries),
                kiss_ate,
                kiss_held,
                ms(row.ours.ms_per_scan),
                ms(kiss.and_then(|k| k.ms_per_scan)),
            )?;
        }
        Ok(())
    }
}

/// Unaligned ATE, or the error that stopped the run.
fn ate(outcome: &Outcome) -> String {
    match &outcome.verdict {
        Ok(v) => format!("{:.3}", v.ate.unaligned),
        Err(reason) => format!("error: {}", reason.replace('|', "/")),
    }
}

/// yes / no with the final error, or "-".
fn held(outcome: &Outcome) -> String {
    match &outcome.verdict {
        Ok(Verdict { held, final_error_m, final_rotation_deg, .. }) => {
            let word = if *held { "yes" } else { "**no**" };
            format!("{word} ({final_error_m:.2} m, {final_rotation_deg:.1}°)")
        }
        Err(_) => "-".into(),
    }
}

fn count(value: Option<usize>) -> String {
    value.map_or("-".into(), |v| v.to_string())
}

fn ms(value: Option<f64>) -> String {
    value.map_or("-".into(), |v| format!("{v:.1}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use edge::odometry::pipeline::AteRmse;

    #[test]
    fn a_failed_case_shows_its_error_and_dashes() {
        let verdict = Verdict {
            ate: AteRmse { unaligned: 0.0412, aligned: Some(0.01) },
            path_m: 11.66,
            final_error_m: 0.05,
            final_rotation_deg: 0.2,
            held: true,
        };
        let kiss = Outcome { verdict: Ok(verdict), ms_per_scan: Some(36.0), ..Outcome::failed(String::new()) };
        let rows = [Row {
            name: "a".into(),
            class: "shuffled".into(),
            scans: 3,
            ours: Outcome::failed("scan 0: no ring channel".into()),
            kiss: Some(kiss),
        }];
        let text = Table(&rows).to_string();
        let last = text.lines().last().unwrap();
        assert_eq!(
            last,
            "| a | shuffled | 3 | 11.7 | error: scan 0: no ring channel | - | - | - | 0.041 | yes (0.05 m, 0.2°) | - | 36.0 |"
        );
    }
}
