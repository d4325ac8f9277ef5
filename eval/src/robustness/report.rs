//! The tables `emr-eval robustness` prints: one row per case and seed, ours beside KISS-ICP, and
//! a summary per part of the matrix with each case's spread over the seeds.

use std::collections::BTreeMap;
use std::fmt;

use cloud::stats::Spread;

use super::matrix::Part;
use super::run::{Outcome, Verdict};

/// One case's results.
#[derive(Clone, Debug, PartialEq)]
pub struct Row {
    /// Case name.
    pub name: String,
    /// Class of hard input.
    pub class: String,
    /// The part of the matrix the case is in.
    pub part: Part,
    /// The seed its noise was drawn from.
    pub seed: u64,
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
                      KISS held | ours ms/scan | KISS ms/scan | part | seed |\n\
                      |---|---|---|---|---|---|---|---|---|---|---|---|---|---|";

impl fmt::Display for Table<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "{HEADER}")?;
        for row in self.0 {
            let kiss = row.kiss.as_ref();
            let (kiss_ate, kiss_held) = kiss.map_or(("-".into(), "-".into()), |k| (ate(k), held(k)));
            writeln!(
                f,
                "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
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
                row.part.name(),
                row.seed,
            )?;
        }
        Ok(())
    }
}

/// Per part of the matrix: how many runs held, ours and KISS-ICP's, the summed unaligned ATE
/// over the runs both finished, and per case the median and range of the ATE over the seeds.
pub struct Summary<'a>(pub &'a [Row]);

impl fmt::Display for Summary<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "| part | runs | ours held | KISS held | ATE sum m, ours / KISS (runs both finished) | cases where ours <= KISS (median over seeds) |"
        )?;
        writeln!(f, "|---|---|---|---|---|---|")?;
        let per_case = self.per_case();
        for part in [Part::Tuned, Part::HeldBack] {
            let rows: Vec<&Row> = self.0.iter().filter(|r| r.part == part).collect();
            if rows.is_empty() {
                continue;
            }
            let held = |o: Option<&Outcome>| o.is_some_and(|o| o.verdict.as_ref().is_ok_and(|v| v.held));
            let ours_held = rows.iter().filter(|r| held(Some(&r.ours))).count();
            let kiss_held = rows.iter().filter(|r| held(r.kiss.as_ref())).count();
            let both: Vec<(f64, f64)> =
                rows.iter().filter_map(|r| Some((unaligned(&r.ours)?, unaligned(r.kiss.as_ref()?)?))).collect();
            let (ours_sum, kiss_sum) = both.iter().fold((0.0, 0.0), |(a, b), (o, k)| (a + o, b + k));
            let cases: Vec<&CaseSpread> = per_case.iter().filter(|c| c.part == part).collect();
            let compared: Vec<&&CaseSpread> = cases.iter().filter(|c| c.kiss.is_some()).collect();
            let no_worse =
                compared.iter().filter(|c| c.ours.zip(c.kiss).is_some_and(|(o, k)| o.median <= k.median)).count();
            writeln!(
                f,
                "| {} | {} | {ours_held} | {} | {ours_sum:.2} / {kiss_sum:.2} ({} runs) | {no_worse} of {} |",
                part.name(),
                rows.len(),
                if rows.iter().any(|r| r.kiss.is_some()) { kiss_held.to_string() } else { "-".into() },
                both.len(),
                compared.len(),
            )?;
        }
        writeln!(f)?;
        writeln!(f, "| case | part | seeds | ours ATE m, median (min-max) | KISS ATE m, median (min-max) |")?;
        writeln!(f, "|---|---|---|---|---|")?;
        for case in &per_case {
            writeln!(
                f,
                "| {} | {} | {} | {} | {} |",
                case.name,
                case.part.name(),
                case.seeds,
                spread(case.ours),
                spread(case.kiss)
            )?;
        }
        Ok(())
    }
}

/// One case's ATE over its seeds.
struct CaseSpread {
    name: String,
    part: Part,
    seeds: usize,
    ours: Option<Range>,
    kiss: Option<Range>,
}

/// Median, least and largest of some runs' ATE.
#[derive(Clone, Copy)]
struct Range {
    median: f64,
    min: f64,
    max: f64,
}

impl Range {
    fn of(values: &[f64]) -> Option<Range> {
        let spread = Spread::of_some(values)?;
        let min = values.iter().copied().fold(f64::INFINITY, f64::min);
        Some(Range { median: spread.median, min, max: spread.max })
    }
}

impl Summary<'_> {
    /// The cases in the order of their first row, each with the spread of its finished runs.
    fn per_case(&self) -> Vec<CaseSpread> {
        let mut order: Vec<&str> = Vec::new();
        let mut runs: BTreeMap<&str, Vec<&Row>> = BTreeMap::new();
        for row in self.0 {
            if !runs.contains_key(row.name.as_str()) {
                order.push(&row.name);
            }
            runs.entry(&row.name).or_default().push(row);
        }
        order
            .into_iter()
            .map(|name| {
                let rows = &runs[name];
                let ours: Vec<f64> = rows.iter().filter_map(|r| unaligned(&r.ours)).collect();
                let kiss: Vec<f64> = rows.iter().filter_map(|r| unaligned(r.kiss.as_ref()?)).collect();
                CaseSpread {
                    name: name.into(),
                    part: rows[0].part,
                    seeds: rows.len(),
                    ours: Range::of(&ours),
                    kiss: Range::of(&kiss),
                }
            })
            .collect()
    }
}

/// The unaligned ATE of a finished run; a track lost to non-finite poses counts as infinite.
fn unaligned(outcome: &Outcome) -> Option<f64> {
    let v = outcome.verdict.as_ref().ok()?;
    Some(if v.ate.unaligned.is_finite() { v.ate.unaligned } else { f64::INFINITY })
}

fn spread(s: Option<Range>) -> String {
    s.map_or("-".into(), |s| format!("{:.3} ({:.3}-{:.3})", s.median, s.min, s.max))
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
            part: Part::Tuned,
            seed: 0,
            scans: 3,
            ours: Outcome::failed("scan 0: no ring channel".into()),
            kiss: Some(kiss),
        }];
        let text = Table(&rows).to_string();
        let last = text.lines().last().unwrap();
        assert_eq!(
            last,
            "| a | shuffled | 3 | 11.7 | error: scan 0: no ring channel | - | - | - | 0.041 | yes (0.05 m, 0.2°) | - | 36.0 | tuned | 0 |"
        );
    }

    fn finished(ate: f64, held: bool) -> Outcome {
        let verdict = Verdict {
            ate: AteRmse { unaligned: ate, aligned: None },
            path_m: 10.0,
            final_error_m: ate,
            final_rotation_deg: 0.1,
            held,
        };
        Outcome { verdict: Ok(verdict), ..Outcome::failed(String::new()) }
    }

    #[test]
    fn the_summary_counts_each_part_and_spreads_each_case_over_its_seeds() {
        let row = |name: &str, part, seed, ours: f64, kiss: f64| Row {
            name: name.into(),
            class: "c".into(),
            part,
            seed,
            scans: 10,
            ours: finished(ours, ours < 1.0),
            kiss: Some(finished(kiss, kiss < 1.0)),
        };
        let rows = [
            row("t", Part::Tuned, 0, 0.1, 0.2),
            row("t", Part::Tuned, 1, 0.3, 0.2),
            row("t", Part::Tuned, 2, 0.2, 0.2),
            row("h", Part::HeldBack, 0, 2.0, 0.5),
            Row { ours: Outcome::failed("broke".into()), ..row("h", Part::HeldBack, 1, 0.0, 0.4) },
        ];
        let text = Summary(&rows).to_string();
        let lines: Vec<&str> = text.lines().collect();
        // Tuned: 3 runs, all held by both; sums 0.6 / 0.6; median 0.2 <= 0.2. (Medians are
        // nearest-rank: of two runs, the lower.)
        assert_eq!(lines[2], "| tuned | 3 | 3 | 3 | 0.60 / 0.60 (3 runs) | 1 of 1 |");
        // Held back: ours lost one run and failed the other; only the run both finished is summed.
        assert_eq!(lines[3], "| held-back | 2 | 0 | 2 | 2.00 / 0.50 (1 runs) | 0 of 1 |");
        assert!(lines.contains(&"| t | tuned | 3 | 0.200 (0.100-0.300) | 0.200 (0.200-0.200) |"), "{text}");
        assert!(lines.contains(&"| h | held-back | 2 | 2.000 (2.000-2.000) | 0.400 (0.400-0.500) |"), "{text}");
    }
}
