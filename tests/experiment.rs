//! `precond experiment --quick` on the icy gridworld, through the real service started
//! in-process on an ephemeral port, writing into a temp dir; the outputs are checked for shape
//! and sanity.

use clap::Parser;
use precond_tools::cli::{Cli, Command};
use serde_json::Value;
use std::collections::HashSet;
use std::path::Path;

const STRATEGIES: [&str; 3] = ["active", "goal_conditioned", "random"];

fn parse_csv(path: &Path) -> (Vec<String>, Vec<Vec<String>>) {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let header: Vec<String> = lines
        .next()
        .expect("a header")
        .split(',')
        .map(String::from)
        .collect();
    let rows: Vec<Vec<String>> = lines
        .map(|l| l.split(',').map(String::from).collect())
        .collect();
    for r in &rows {
        assert_eq!(r.len(), header.len(), "{}: {r:?}", path.display());
    }
    (header, rows)
}

/// Runs `precond experiment --quick --no-progress ARGS --out OUT` and returns the directory
/// it wrote its results to.
async fn run_quick(args: &[&str], out: &Path) -> std::path::PathBuf {
    let argv = ["precond", "experiment", "--quick", "--no-progress"]
        .into_iter()
        .chain(args.iter().copied())
        .chain(["--out", out.to_str().unwrap()]);
    let cli = Cli::try_parse_from(argv).unwrap();
    let Command::Experiment(args) = cli.command else {
        panic!("not the experiment command");
    };
    precond_tools::experiment::run(args).await.unwrap()
}

fn is_rate(x: f64) -> bool {
    (0.0..=1.0).contains(&x)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_quick_gridworld_experiment_writes_well_formed_results_and_plots() {
    let dir = tempfile::tempdir().unwrap();
    let out = run_quick(&["--domain", "icy_gridworld", "--jobs", "2"], dir.path()).await;
    assert_eq!(out, dir.path().join("icy_gridworld"));

    // iterations.csv: one row per strategy × seed × iteration, the documented columns.
    let (header, rows) = parse_csv(&out.join("iterations.csv"));
    assert_eq!(header, precond_tools::experiment::report::ITERATION_COLUMNS);
    let col = |name: &str| header.iter().position(|h| h == name).unwrap();
    assert_eq!(rows.len(), 3 * 2 * 3);
    let keys: HashSet<(String, String, String)> = rows
        .iter()
        .map(|r| {
            (
                r[col("strategy")].clone(),
                r[col("seed")].clone(),
                r[col("iteration")].clone(),
            )
        })
        .collect();
    assert_eq!(keys.len(), rows.len());
    for r in &rows {
        assert_eq!(r[col("domain")], "icy_gridworld");
        assert!(STRATEGIES.contains(&r[col("strategy")].as_str()));
        for rate in [
            "plan_found_rate",
            "success_rate",
            "unsafe_step_rate",
            "tpr",
            "tnr",
        ] {
            let v = &r[col(rate)];
            if !v.is_empty() {
                assert!(is_rate(v.parse().unwrap()), "{rate} = {v}");
            }
        }
        let found: usize = r[col("plans_found")].parse().unwrap();
        let ok: usize = r[col("successes")].parse().unwrap();
        assert!(ok <= found && found <= 3, "{r:?}");
        let planned: usize = r[col("planned_steps")].parse().unwrap();
        let wrong: usize = r[col("unsafe_planned_steps")].parse().unwrap();
        assert!(wrong <= planned && (found > 0) == (planned > 0), "{r:?}");
        let n_train: usize = r[col("n_train")].parse().unwrap();
        assert!(n_train > 0, "the model was refit: {r:?}");
        let covered: usize = r[col("model_trajectories")].parse().unwrap();
        let posted: usize = r[col("train_trajectories")].parse().unwrap();
        assert!(
            covered >= posted,
            "the evaluated model covers the batch: {r:?}"
        );
        assert!(r[col("held_out")].parse::<usize>().unwrap() > 0);
    }

    // The per-slot and per-problem files.
    let (_, training) = parse_csv(&out.join("training.csv"));
    assert_eq!(training.len(), 3 * 2 * 3 * 5);
    let (test_header, tests) = parse_csv(&out.join("tests.csv"));
    assert_eq!(tests.len(), 3 * 2 * 3 * 3);
    // Each iteration's planned and unsafe steps are its test plans' own.
    let tcol = |name: &str| test_header.iter().position(|h| h == name).unwrap();
    for r in &rows {
        let of_iteration = tests.iter().filter(|t| {
            t[tcol("strategy")] == r[col("strategy")]
                && t[tcol("seed")] == r[col("seed")]
                && t[tcol("iteration")] == r[col("iteration")]
        });
        let (mut planned, mut wrong) = (0usize, 0usize);
        for t in of_iteration {
            let length: usize = t[tcol("plan_length")].parse().unwrap();
            let unsafe_steps: usize = t[tcol("unsafe_steps")].parse().unwrap();
            assert!(unsafe_steps <= length, "{t:?}");
            planned += length;
            wrong += unsafe_steps;
        }
        assert_eq!(r[col("planned_steps")], planned.to_string());
        assert_eq!(r[col("unsafe_planned_steps")], wrong.to_string());
    }

    // summary.json: every strategy, every iteration, every metric; rates in [0, 1].
    let summary: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["domain"], "icy_gridworld");
    for s in STRATEGIES {
        for m in precond_tools::experiment::report::METRICS {
            let series = summary["strategies"][s][m].as_array().unwrap();
            assert_eq!(series.len(), 3, "{s} {m}");
            for (j, point) in series.iter().enumerate() {
                assert_eq!(point["iteration"], j);
                if ["plan_found_rate", "success_rate", "tpr", "tnr"].contains(&m)
                    && let Some(mean) = point["mean"].as_f64()
                {
                    assert!(is_rate(mean), "{s} {m} {point}");
                    assert!(point["se"].as_f64().unwrap() >= 0.0);
                }
            }
        }
        assert_eq!(summary["strategies"][s]["plan_found_rate"][0]["n"], 2);
    }
    // The closing table the command prints: one row per strategy with the final figures.
    let table = precond_tools::experiment::report::summary_table_of(&out).unwrap();
    let table_rows: Vec<&str> = table.lines().skip(2).collect();
    assert_eq!(table_rows.len(), STRATEGIES.len(), "{table}");
    for (row, s) in table_rows.iter().zip(STRATEGIES) {
        assert!(row.starts_with(s), "{table}");
        let tpr = &summary["final"][s]["tpr"];
        if let (Some(m), Some(se)) = (tpr["mean"].as_f64(), tpr["se"].as_f64()) {
            assert!(row.contains(&format!("{m:.2} ± {se:.2}")), "{s}: {table}");
        }
    }

    // The plots.
    for name in ["metrics.svg", "training.svg"] {
        let svg = std::fs::read_to_string(out.join(name)).unwrap();
        assert!(svg.starts_with("<svg") && svg.len() > 1000, "{name}");
        assert!(svg.contains("plan found") || name != "metrics.svg");
    }

    // Deterministic: a second run gives the same measurements.
    let again = tempfile::tempdir().unwrap();
    let out2 = run_quick(&["--strategies", "active", "--seeds", "1"], again.path()).await;
    let (_, rows2) = parse_csv(&out2.join("iterations.csv"));
    let first: Vec<&Vec<String>> = rows
        .iter()
        .filter(|r| r[col("strategy")] == "active" && r[col("seed")] == "0")
        .collect();
    assert_eq!(rows2.len(), 3);
    for (a, b) in first.iter().zip(&rows2) {
        // Everything but the wall-clock seconds.
        assert_eq!(a[..a.len() - 1], b[..b.len() - 1]);
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_quick_water_plant_experiment_draws_the_precondition_maps() {
    let dir = tempfile::tempdir().unwrap();
    let out = run_quick(
        &["--domain", "water_plant", "--strategies", "active,random"],
        dir.path(),
    )
    .await;
    let (header, rows) = parse_csv(&out.join("iterations.csv"));
    assert_eq!(rows.len(), 2 * 2 * 3);
    // Every executed training trajectory has a type.
    let col = |name: &str| header.iter().position(|h| h == name).unwrap();
    for r in &rows {
        let typed: usize = [
            "no_pour",
            "below_success",
            "below_spill",
            "above_success",
            "above_spill",
        ]
        .iter()
        .map(|c| r[col(c)].parse::<usize>().unwrap())
        .sum();
        assert_eq!(
            typed,
            r[col("train_trajectories")].parse::<usize>().unwrap()
        );
    }
    // Maps at the first and last iterations (quick: 0 and 2) of seed 0's active run.
    let maps: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("maps.json")).unwrap()).unwrap();
    let maps = maps.as_array().unwrap();
    assert_eq!(maps.len(), 2 * 2);
    for m in maps {
        let (nx, ny) = (
            m["xs"].as_array().unwrap().len(),
            m["ys"].as_array().unwrap().len(),
        );
        let upper = m["upper"].as_array().unwrap();
        assert_eq!(upper.len(), ny);
        assert!(upper.iter().all(|row| row.as_array().unwrap().len() == nx));
    }
    for name in [
        "metrics.svg",
        "training.svg",
        "trajectory_types.svg",
        "precondition_map_0.svg",
        "precondition_map_2.svg",
    ] {
        let svg = std::fs::read_to_string(out.join(name)).unwrap();
        assert!(svg.starts_with("<svg") && svg.len() > 1000, "{name}");
    }
}

/// On a continuous world the share solvable inside the learned precondition comes from a
/// search ten times longer than the planner's: every problem the planner solved counts, and a
/// problem counts only if one of the two searches found a plan.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_continuous_world_reports_what_a_long_search_finds_inside_the_learned_precondition() {
    let dir = tempfile::tempdir().unwrap();
    let out = run_quick(
        &[
            "--domain",
            "pusher",
            "--seeds",
            "1",
            "--strategies",
            "active",
            "--test-problems",
            "6",
            "--max-extensions",
            "300",
            "--jobs",
            "2",
        ],
        dir.path(),
    )
    .await;
    let (header, rows) = parse_csv(&out.join("iterations.csv"));
    let col = |name: &str| header.iter().position(|h| h == name).unwrap();
    assert_eq!(rows.len(), 3);
    for r in &rows {
        let found: usize = r[col("plans_found")].parse().unwrap();
        let learned: usize = r[col("learned_solvable")].parse().unwrap();
        assert!(found <= learned && learned <= 6, "{r:?}");
        let rate: f64 = r[col("learned_rate")].parse().unwrap();
        assert!((rate - learned as f64 / 6.0).abs() < 1e-9, "{r:?}");
    }
    let (test_header, tests) = parse_csv(&out.join("tests.csv"));
    let tcol = |name: &str| test_header.iter().position(|h| h == name).unwrap();
    assert_eq!(tests.len(), 3 * 6);
    for t in &tests {
        let learned = &t[tcol("learned")];
        assert!(learned == "true" || learned == "false", "{t:?}");
        if t[tcol("found")] == "true" {
            assert_eq!(learned, "true", "a plan found is inside: {t:?}");
        }
    }
}
