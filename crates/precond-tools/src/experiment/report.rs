//! What a harness run writes: `iterations.csv` (one row per strategy × seed × iteration),
//! `training.csv` (one row per training slot), `tests.csv` (one row per test problem; vectors
//! as `;`-separated numbers),
//! `summary.json` (mean and standard error over seeds per strategy, iteration and metric) and,
//! for the water plant, `maps.json` (the precondition maps behind the map figures).

use super::Results;
use super::protocol::{IterationRecord, PourType, TestRecord, TrainingRecord};
use anyhow::Context;
use precond_core::planning::Strategy;
use serde_json::{Map, Value, json};
use std::fmt::Write as _;
use std::path::Path;

/// A summary metric: its name and its value in an iteration record (nothing where the record
/// does not know it).
type Metric = (&'static str, fn(&IterationRecord) -> Option<f64>);

/// The metrics of the summary, each named beside its value.
const METRIC_VALUES: [Metric; 33] = [
    ("plan_found_rate", |r| Some(r.plan_found_rate)),
    ("unsafe_step_rate", |r| r.unsafe_step_rate),
    ("success_rate", |r| Some(r.success_rate)),
    ("oracle_rate", |r| r.oracle_rate),
    ("success_of_oracle", |r| {
        (r.oracle_solvable > 0).then(|| r.successes as f64 / r.oracle_solvable as f64)
    }),
    ("learned_rate", |r| r.learned_rate),
    ("learned_of_oracle", |r| {
        r.learned_rate
            .filter(|_| r.oracle_solvable > 0)
            .map(|_| r.learned_solvable as f64 / r.oracle_solvable as f64)
    }),
    ("plans_of_learned", |r| {
        r.learned_rate
            .filter(|_| r.learned_solvable > 0)
            .map(|_| r.plans_found as f64 / r.learned_solvable as f64)
    }),
    // Known where the learned search is exhaustive and the oracle known (gridworlds).
    ("one_move_short_rate", |r| {
        r.oracle_rate
            .and(r.learned_rate)
            .map(|_| r.one_move_short as f64 / r.test_problems.max(1) as f64)
    }),
    ("one_move_short_executed_rate", |r| {
        r.oracle_rate
            .and(r.learned_rate)
            .map(|_| r.one_move_short_executed as f64 / r.test_problems.max(1) as f64)
    }),
    ("closed_loop_rate", |r| r.closed_loop_rate),
    ("oracle_open_loop_rate", |r| {
        r.oracle_rate
            .map(|_| r.oracle_open_successes as f64 / r.test_problems.max(1) as f64)
    }),
    ("oracle_closed_loop_rate", |r| {
        r.oracle_rate
            .map(|_| r.oracle_closed_successes as f64 / r.test_problems.max(1) as f64)
    }),
    ("baseline_rate", |r| r.baseline_rate),
    ("plans_of_oracle", |r| {
        (r.oracle_solvable > 0).then(|| r.plans_found as f64 / r.oracle_solvable as f64)
    }),
    ("closed_loop_of_oracle", |r| {
        r.closed_loop_rate
            .filter(|_| r.oracle_solvable > 0)
            .map(|_| r.closed_loop_successes as f64 / r.oracle_solvable as f64)
    }),
    ("open_loop_of_oracle_open_loop", |r| {
        (r.oracle_open_successes > 0).then(|| r.successes as f64 / r.oracle_open_successes as f64)
    }),
    ("held_out_median_sigma", |r| r.held_out_median_sigma),
    ("test_beta", |r| r.test_beta),
    ("replans", |r| r.closed_loop_rate.map(|_| r.replans as f64)),
    ("tpr", |r| r.tpr),
    ("tnr", |r| r.tnr),
    ("train_no_plan", |r| Some(r.train_no_plan as f64)),
    ("train_skipped", |r| Some(r.train_skipped as f64)),
    ("train_relaxed", |r| Some(r.train_relaxed as f64)),
    ("mean_traj_length", |r| r.mean_traj_length),
    ("train_goal_rate", |r| {
        (r.train_trajectories > 0)
            .then(|| r.train_goal_reached as f64 / r.train_trajectories as f64)
    }),
    ("n_train", |r| Some(r.n_train as f64)),
    ("model_version", |r| Some(r.model_version as f64)),
    ("below_success_ratio", |r| {
        pour_ratio(r, PourType::BelowSuccess)
    }),
    ("below_spill_ratio", |r| pour_ratio(r, PourType::BelowSpill)),
    ("above_spill_ratio", |r| pour_ratio(r, PourType::AboveSpill)),
    ("no_pour_ratio", |r| pour_ratio(r, PourType::NoPour)),
];

/// The metrics of the summary, each a number (or nothing) per iteration record.
pub const METRICS: [&str; 33] = {
    let mut names = [""; 33];
    let mut i = 0;
    while i < METRIC_VALUES.len() {
        names[i] = METRIC_VALUES[i].0;
        i += 1;
    }
    names
};

/// A CSV column: its name and its text in a row of `R`.
type Column<R> = (&'static str, fn(&R) -> String);

/// The columns of `iterations.csv` after `domain` and `layout`: each name beside its value, in
/// order, so that a column cannot be named in one list and filled from another.
const RECORD_COLUMNS: [Column<IterationRecord>; 50] = [
    ("strategy", |r| r.strategy.as_str().to_string()),
    ("seed", |r| r.seed.to_string()),
    ("iteration", |r| r.iteration.to_string()),
    ("beta_train", |r| opt(r.beta_train)),
    ("train_trajectories", |r| r.train_trajectories.to_string()),
    ("train_no_plan", |r| r.train_no_plan.to_string()),
    ("train_skipped", |r| r.train_skipped.to_string()),
    ("train_relaxed", |r| r.train_relaxed.to_string()),
    ("mean_traj_length", |r| opt(r.mean_traj_length)),
    ("train_goal_reached", |r| r.train_goal_reached.to_string()),
    ("train_high_deviation", |r| {
        r.train_high_deviation.to_string()
    }),
    ("n_train", |r| r.n_train.to_string()),
    ("model_version", |r| r.model_version.to_string()),
    ("model_trajectories", |r| r.model_trajectories.to_string()),
    ("test_problems", |r| r.test_problems.to_string()),
    ("plans_found", |r| r.plans_found.to_string()),
    ("successes", |r| r.successes.to_string()),
    ("plan_found_rate", |r| r.plan_found_rate.to_string()),
    ("success_rate", |r| r.success_rate.to_string()),
    ("planned_steps", |r| r.planned_steps.to_string()),
    ("unsafe_planned_steps", |r| {
        r.unsafe_planned_steps.to_string()
    }),
    ("unsafe_step_rate", |r| opt(r.unsafe_step_rate)),
    ("oracle_solvable", |r| r.oracle_solvable.to_string()),
    ("oracle_rate", |r| opt(r.oracle_rate)),
    ("learned_solvable", |r| r.learned_solvable.to_string()),
    ("learned_rate", |r| opt(r.learned_rate)),
    ("one_move_short", |r| r.one_move_short.to_string()),
    ("one_move_short_executed", |r| {
        r.one_move_short_executed.to_string()
    }),
    ("closed_loop_successes", |r| {
        r.closed_loop_successes.to_string()
    }),
    ("closed_loop_rate", |r| opt(r.closed_loop_rate)),
    ("replans", |r| r.replans.to_string()),
    ("oracle_open_successes", |r| {
        r.oracle_open_successes.to_string()
    }),
    ("oracle_closed_successes", |r| {
        r.oracle_closed_successes.to_string()
    }),
    ("baseline_successes", |r| r.baseline_successes.to_string()),
    ("baseline_rate", |r| opt(r.baseline_rate)),
    ("held_out_median_sigma", |r| opt(r.held_out_median_sigma)),
    ("test_beta", |r| opt(r.test_beta)),
    ("held_out", |r| r.held_out.to_string()),
    ("held_out_low", |r| r.held_out_low.to_string()),
    ("held_out_high", |r| r.held_out_high.to_string()),
    ("true_positives", |r| r.true_positives.to_string()),
    ("true_negatives", |r| r.true_negatives.to_string()),
    ("tpr", |r| opt(r.tpr)),
    ("tnr", |r| opt(r.tnr)),
    ("no_pour", |r| r.pour_types[0].to_string()),
    ("below_success", |r| r.pour_types[1].to_string()),
    ("below_spill", |r| r.pour_types[2].to_string()),
    ("above_success", |r| r.pour_types[3].to_string()),
    ("above_spill", |r| r.pour_types[4].to_string()),
    ("seconds", |r| format!("{:.3}", r.seconds)),
];

/// The columns of `iterations.csv`.
pub const ITERATION_COLUMNS: [&str; 52] = {
    let mut names = [""; 52];
    (names[0], names[1]) = ("domain", "layout");
    let mut i = 0;
    while i < RECORD_COLUMNS.len() {
        names[i + 2] = RECORD_COLUMNS[i].0;
        i += 1;
    }
    names
};

/// The columns of `training.csv` after `domain`.
const TRAINING_COLUMNS: [Column<TrainingRecord>; 11] = [
    ("strategy", |t| t.strategy.as_str().to_string()),
    ("seed", |t| t.seed.to_string()),
    ("iteration", |t| t.iteration.to_string()),
    ("slot", |t| t.slot.to_string()),
    ("no_plan", |t| t.no_plan.to_string()),
    ("beta", |t| opt(t.beta)),
    ("executed", |t| t.executed.to_string()),
    ("length", |t| t.length.to_string()),
    ("goal_reached", |t| t.goal_reached.to_string()),
    ("max_deviation", |t| t.max_deviation.to_string()),
    ("pour_type", |t| t.pour_type.as_str().to_string()),
];

/// The columns of `tests.csv` after `domain` (vectors as `;`-separated numbers).
const TEST_COLUMNS: [Column<TestRecord>; 20] = [
    ("strategy", |t| t.strategy.as_str().to_string()),
    ("seed", |t| t.seed.to_string()),
    ("iteration", |t| t.iteration.to_string()),
    ("problem", |t| t.problem.to_string()),
    ("start", |t| vector(&t.start)),
    ("goal", |t| vector(&t.goal)),
    ("found", |t| t.found.to_string()),
    ("extensions", |t| t.extensions.to_string()),
    ("plan_length", |t| t.plan_length.to_string()),
    ("success", |t| t.success.to_string()),
    ("oracle", |t| flag(t.oracle)),
    ("learned", |t| flag(t.learned)),
    ("blocking_moves", |t| {
        t.blocking.map_or(String::new(), |b| b.0.to_string())
    }),
    ("blocking_executed", |t| {
        t.blocking.map_or(String::new(), |b| b.1.to_string())
    }),
    ("unsafe_steps", |t| t.unsafe_steps.to_string()),
    ("closed_loop_success", |t| flag(t.closed_loop_success)),
    ("replans", |t| t.replans.to_string()),
    ("oracle_open_loop", |t| flag(t.oracle_open_loop)),
    ("oracle_closed_loop", |t| flag(t.oracle_closed_loop)),
    ("baseline", |t| flag(t.baseline)),
];

/// A CSV table: the `fixed` columns (a name and the one value every row has) then `columns`,
/// a header line and a line per row.
fn table<'a, R: 'a>(
    fixed: &[(&str, &str)],
    columns: &[Column<R>],
    rows: impl Iterator<Item = &'a R>,
) -> String {
    let names = fixed.iter().map(|(name, _)| *name);
    let mut csv = names
        .chain(columns.iter().map(|(name, _)| *name))
        .collect::<Vec<_>>()
        .join(",");
    csv.push('\n');
    for row in rows {
        let values = fixed.iter().map(|(_, value)| value.to_string());
        let values: Vec<String> = values
            .chain(columns.iter().map(|(_, value)| value(row)))
            .collect();
        csv += &values.join(",");
        csv.push('\n');
    }
    csv
}

/// A vector as `;`-separated numbers.
fn vector(v: &[f64]) -> String {
    v.iter()
        .map(|x| format!("{x}"))
        .collect::<Vec<_>>()
        .join(";")
}

fn pour_ratio(r: &IterationRecord, kind: PourType) -> Option<f64> {
    let k = PourType::ALL.iter().position(|p| *p == kind)?;
    (r.train_trajectories > 0).then(|| r.pour_types[k] as f64 / r.train_trajectories as f64)
}

/// The value of `metric` (one of [`METRICS`]) in a record.
pub fn metric(r: &IterationRecord, metric: &str) -> Option<f64> {
    METRIC_VALUES
        .iter()
        .find(|(name, _)| *name == metric)
        .and_then(|(_, value)| value(r))
}

/// Mean, standard error of the mean (sample standard deviation / √n; 0 when n = 1) and n of
/// the values present.
pub fn mean_se(values: impl IntoIterator<Item = Option<f64>>) -> Option<(f64, f64, usize)> {
    let v: Vec<f64> = values
        .into_iter()
        .flatten()
        .filter(|x| x.is_finite())
        .collect();
    let n = v.len();
    if n == 0 {
        return None;
    }
    let mean = v.iter().sum::<f64>() / n as f64;
    let se = if n > 1 {
        let var = v.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / (n - 1) as f64;
        (var / n as f64).sqrt()
    } else {
        0.0
    };
    Some((mean, se, n))
}

/// Every iteration record of `strategy`, grouped by iteration.
pub fn by_iteration(results: &Results, strategy: Strategy) -> Vec<Vec<&IterationRecord>> {
    let mut out = vec![Vec::new(); results.config.iterations];
    for run in &results.runs {
        for r in run.iterations.iter().filter(|r| r.strategy == strategy) {
            if let Some(slot) = out.get_mut(r.iteration) {
                slot.push(r);
            }
        }
    }
    out
}

fn flag(v: Option<bool>) -> String {
    v.map_or_else(String::new, |o| o.to_string())
}

fn opt(v: Option<f64>) -> String {
    v.map_or_else(String::new, |v| format!("{v}"))
}

fn write(path: &Path, text: &str) -> anyhow::Result<()> {
    std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))
}

/// Writes every file of a run into `dir`.
pub fn write_all(dir: &Path, results: &Results) -> anyhow::Result<()> {
    let domain = results.config.domain.as_str();
    let layout = results.config.layout_name();
    let iterations = results.runs.iter().flat_map(|run| &run.iterations);
    let csv = table(
        &[("domain", domain), ("layout", layout)],
        &RECORD_COLUMNS,
        iterations,
    );
    write(&dir.join("iterations.csv"), &csv)?;

    let training = results.runs.iter().flat_map(|run| &run.training);
    let csv = table(&[("domain", domain)], &TRAINING_COLUMNS, training);
    write(&dir.join("training.csv"), &csv)?;

    let tests = results.runs.iter().flat_map(|run| &run.tests);
    let csv = table(&[("domain", domain)], &TEST_COLUMNS, tests);
    write(&dir.join("tests.csv"), &csv)?;

    let summary = summary(results);
    write(
        &dir.join("summary.json"),
        &serde_json::to_string_pretty(&summary)?,
    )?;

    let maps: Vec<_> = results.runs.iter().flat_map(|r| &r.maps).collect();
    if !maps.is_empty() {
        write(&dir.join("maps.json"), &serde_json::to_string(&maps)?)?;
    }
    Ok(())
}

/// The metrics `layouts.csv` compares.
pub const LAYOUT_METRICS: [&str; 8] = [
    "success_rate",
    "plan_found_rate",
    "oracle_rate",
    "success_of_oracle",
    "learned_of_oracle",
    "tpr",
    "tnr",
    "n_train",
];

/// Writes `layouts.csv` into `dir`: per layout (and `all`, pooling every layout's runs),
/// strategy and iteration, the mean and standard error over seeds of [`LAYOUT_METRICS`]; and
/// prints the last iteration's success against the oracle per layout and strategy.
pub fn write_layouts(dir: &Path, all: &[Results]) -> anyhow::Result<()> {
    let mut csv = String::from("layout,strategy,iteration,n");
    for m in LAYOUT_METRICS {
        let _ = write!(csv, ",{m},{m}_se");
    }
    csv.push('\n');
    let Some(first) = all.first() else {
        return write(&dir.join("layouts.csv"), &csv);
    };
    let cfg = &first.config;
    let mut groups: Vec<(&str, Vec<&Results>)> = all
        .iter()
        .map(|r| (r.config.layout_name(), vec![r]))
        .collect();
    groups.push(("all", all.iter().collect()));
    for (name, results) in &groups {
        for &s in &cfg.strategies {
            let mut per_iteration = vec![Vec::new(); cfg.iterations];
            for r in results {
                for (j, g) in by_iteration(r, s).into_iter().enumerate() {
                    per_iteration[j].extend(g);
                }
            }
            for (j, recs) in per_iteration.iter().enumerate() {
                let _ = write!(csv, "{name},{},{j},{}", s.as_str(), recs.len());
                for m in LAYOUT_METRICS {
                    match mean_se(recs.iter().map(|r| metric(r, m))) {
                        Some((mean, se, _)) => {
                            let _ = write!(csv, ",{mean},{se}");
                        }
                        None => csv.push_str(",,"),
                    }
                }
                csv.push('\n');
                if j + 1 == cfg.iterations {
                    let success = mean_se(recs.iter().map(|r| metric(r, "success_rate")));
                    let oracle = mean_se(recs.iter().map(|r| metric(r, "oracle_rate")));
                    let tnr = mean_se(recs.iter().map(|r| metric(r, "tnr")));
                    eprintln!(
                        "{name:>10} {:<16} iteration {j}: success {} of oracle {}, TNR {}",
                        s.as_str(),
                        fmt_stat(success),
                        fmt_stat(oracle),
                        fmt_stat(tnr)
                    );
                }
            }
        }
    }
    write(&dir.join("layouts.csv"), &csv)
}

fn fmt_stat(s: Option<(f64, f64, usize)>) -> String {
    s.map_or_else(|| "-".into(), |(m, se, _)| format!("{m:.2} ± {se:.2}"))
}

/// The JSON summary: settings, run time, and per strategy per metric a list over iterations of
/// `{iteration, mean, se, n}` (`mean`/`se` null when no seed had a value), plus the final
/// iteration's figures under `final`.
pub fn summary(results: &Results) -> Value {
    let cfg = &results.config;
    let mut strategies = Map::new();
    let mut finals = Map::new();
    for &s in &cfg.strategies {
        let groups = by_iteration(results, s);
        let mut per_metric = Map::new();
        let mut fin = Map::new();
        for m in METRICS {
            let series: Vec<Value> = groups
                .iter()
                .enumerate()
                .map(|(j, g)| {
                    let stat = mean_se(g.iter().map(|r| metric(r, m)));
                    json!({
                        "iteration": j,
                        "mean": stat.map(|x| x.0),
                        "se": stat.map(|x| x.1),
                        "n": stat.map_or(0, |x| x.2),
                    })
                })
                .collect();
            if let Some(last) = series.last() {
                fin.insert(m.to_string(), last.clone());
            }
            per_metric.insert(m.to_string(), Value::Array(series));
        }
        strategies.insert(s.as_str().to_string(), Value::Object(per_metric));
        finals.insert(s.as_str().to_string(), Value::Object(fin));
    }
    json!({
        "domain": cfg.domain.as_str(),
        "layout": cfg.layout_name(),
        "config": cfg,
        "server": results.server,
        "seconds": results.seconds,
        "held_out_pool_sizes": results.pool_sizes,
        "metrics": METRICS.as_slice(),
        "strategies": strategies,
        "final": finals,
    })
}

/// The columns of the closing table: `(metric of the summary, heading)`.
pub const TABLE_COLUMNS: [(&str, &str); 6] = [
    ("plan_found_rate", "plan found"),
    ("success_rate", "success"),
    ("closed_loop_rate", "closed loop"),
    ("oracle_rate", "oracle"),
    ("tpr", "TPR"),
    ("tnr", "TNR"),
];

/// The closing table of a run, read from its `summary.json`: per strategy, the final
/// iteration's plan-found, success, closed-loop success and oracle rates and the precondition's
/// TPR and TNR, as mean ± standard error over seeds (`–` where no seed had a value, e.g. the
/// oracle of a world without one).
pub fn summary_table(summary: &Value) -> String {
    let strategies: Vec<&str> = summary["config"]["strategies"]
        .as_array()
        .map(|s| s.iter().filter_map(Value::as_str).collect())
        .unwrap_or_default();
    let iterations = summary["config"]["iterations"].as_u64().unwrap_or(0);
    let seeds = summary["config"]["seeds"].as_u64().unwrap_or(0);
    let mut out = format!(
        "{} ({}), iteration {} (the last), mean ± se over {seeds} seed{}:\n",
        summary["domain"].as_str().unwrap_or("?"),
        summary["layout"].as_str().unwrap_or("default"),
        iterations.saturating_sub(1),
        if seeds == 1 { "" } else { "s" },
    );
    let width = strategies.iter().map(|s| s.len()).max().unwrap_or(0).max(8);
    let _ = write!(out, "{:<width$}", "strategy");
    for (_, heading) in TABLE_COLUMNS {
        let _ = write!(out, "  {heading:>13}");
    }
    out.push('\n');
    for s in strategies {
        let _ = write!(out, "{s:<width$}");
        for (metric, _) in TABLE_COLUMNS {
            let m = &summary["final"][s][metric];
            let cell = match (m["mean"].as_f64(), m["se"].as_f64()) {
                (Some(mean), Some(se)) => format!("{mean:.2} ± {se:.2}"),
                (Some(mean), None) => format!("{mean:.2}"),
                _ => "–".to_string(),
            };
            let _ = write!(out, "  {cell:>13}");
        }
        out.push('\n');
    }
    out
}

/// Reads `dir/summary.json` back and returns its closing table ([`summary_table`]).
pub fn summary_table_of(dir: &Path) -> anyhow::Result<String> {
    let path = dir.join("summary.json");
    let text =
        std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let summary: Value =
        serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
    Ok(summary_table(&summary))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_closing_table_shows_each_strategys_final_figures() {
        let stat = |mean: Option<f64>| json!({"iteration": 2, "mean": mean, "se": mean.map(|_| 0.05), "n": 2});
        let mut fin = Map::new();
        for (metric, _) in TABLE_COLUMNS {
            fin.insert(
                metric.into(),
                stat((metric != "oracle_rate").then_some(0.5)),
            );
        }
        let summary = json!({
            "domain": "icy_gridworld", "layout": "default",
            "config": {"strategies": ["active", "random"], "iterations": 3, "seeds": 2},
            "final": {"active": fin, "random": {"tpr": stat(Some(0.25))}},
        });
        let table = summary_table(&summary);
        let lines: Vec<&str> = table.lines().collect();
        assert_eq!(lines.len(), 4, "{table}");
        assert!(
            lines[0].contains("iteration 2") && lines[0].contains("2 seeds"),
            "{table}"
        );
        for (_, heading) in TABLE_COLUMNS {
            assert!(lines[1].contains(heading), "{table}");
        }
        assert!(lines[2].starts_with("active"));
        assert_eq!(lines[2].matches("0.50 ± 0.05").count(), 5, "{table}");
        assert_eq!(lines[2].matches('–').count(), 1, "no oracle: {table}");
        assert!(lines[3].starts_with("random") && lines[3].contains("0.25 ± 0.05"));
        assert_eq!(lines[3].matches('–').count(), 5, "{table}");
    }

    #[test]
    fn mean_and_standard_error() {
        let (m, se, n) = mean_se([Some(1.0), Some(3.0), None]).unwrap();
        assert_eq!((m, n), (2.0, 2));
        // Sample sd √2, se = √2 / √2 = 1.
        assert!((se - 1.0).abs() < 1e-12);
        assert_eq!(mean_se([Some(0.5)]), Some((0.5, 0.0, 1)));
        assert_eq!(mean_se([None]), None);
    }
}
