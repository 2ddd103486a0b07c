//! `precond import` against a real server: CSV and Parquet files into an experiment, the
//! transitions read back equal with their labels and provenance, a re-run (or an interrupted
//! run resumed) stores nothing twice, long episodes are split, and bad input is named.

use crate::helpers::*;
use clap::Parser;
use parquet::basic::{Compression, ConvertedType, LogicalType, Repetition, Type as Physical};
use parquet::column::writer::ColumnWriter;
use parquet::file::properties::WriterProperties;
use parquet::file::writer::SerializedFileWriter;
use parquet::schema::types::Type;
use precond_tools::cli::{Cli, Command};
use precond_tools::import::ImportReport;
use serde_json::{Value, json};
use std::path::Path;
use std::sync::Arc;

/// One logged step: episode, s, a, s_next.
type Step = (i64, [f64; 2], [f64; 2], [f64; 2]);

/// Episodes of a robot whose pushes go 80 % of the way (the kinematic model expects all of it).
fn logged(lengths: &[usize]) -> Vec<Step> {
    let mut out = Vec::new();
    for (e, &n) in lengths.iter().enumerate() {
        let mut s = [0.1 + 0.05 * e as f64, 0.2];
        for k in 0..n {
            let a = [0.05, if k % 2 == 0 { 0.03 } else { -0.02 }];
            let next = [s[0] + 0.8 * a[0], s[1] + 0.8 * a[1]];
            out.push((e as i64 * 10, s, a, next));
            s = next;
        }
    }
    out
}

fn write_csv(path: &Path, steps: &[Step]) {
    let mut text = String::from("episode,s_x,s_y,a_dx,a_dy,s_next_x,s_next_y\n");
    for (e, s, a, n) in steps {
        text += &format!(
            "{e},{},{},{},{},{},{}\n",
            s[0], s[1], a[0], a[1], n[0], n[1]
        );
    }
    std::fs::write(path, text).unwrap();
}

async fn import(
    app: &TestApp,
    id: i64,
    extra: &[&str],
    files: &[&Path],
) -> anyhow::Result<ImportReport> {
    let url = app.url("");
    let id = id.to_string();
    let mut argv = vec![
        "precond",
        "import",
        "--experiment",
        &id,
        "--server",
        &url,
        "--no-progress",
    ];
    argv.extend(extra);
    let files: Vec<String> = files.iter().map(|f| f.display().to_string()).collect();
    argv.extend(files.iter().map(String::as_str));
    let Command::Import(args) = Cli::try_parse_from(argv).unwrap().command else {
        panic!("not the import command");
    };
    precond_tools::import::run(args).await
}

fn vec2(v: &Value) -> [f64; 2] {
    serde_json::from_value(v.clone()).unwrap()
}

async fn kinematic(app: &TestApp) -> i64 {
    app.create_experiment(json!({
        "domain": {"kind": "kinematic", "state_high": [2, 2]},
        "learning": {"batch_size": 1000}
    }))
    .await
}

#[tokio::test]
async fn a_csv_import_round_trips_with_labels_and_provenance_and_runs_once() {
    let (dir, db) = temp_db();
    let app = spawn_app(&db).await;
    let id = kinematic(&app).await;
    let steps = logged(&[4, 3, 9]);
    let csv = dir.path().join("pushes.csv");
    write_csv(&csv, &steps);

    // An earlier run was interrupted after the first episode: it is recognised, not repeated.
    let dataset = precond_tools::import::default_dataset_name(&csv);
    let dataset_id = precond_tools::import::dataset_identity(&dataset);
    let first: Vec<Value> = steps[..4]
        .iter()
        .map(|(_, s, a, n)| json!({"s": s, "a": a, "s_next": n}))
        .collect();
    let r = app
        .client
        .post(app.url(&format!("/v1/experiments/{id}/trajectories")))
        .header("idempotency-key", format!("import-{dataset_id}-0-0"))
        .json(&json!({
            "source": {"dataset": dataset, "episode": 0, "first_step": 0, "label": "bench"},
            "transitions": first
        }))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);

    let bench = ["--label", "bench", "--max-transitions", "4"];
    let report = import(&app, id, &bench, &[&csv]).await.unwrap();
    // Episode 20 has 9 transitions: 3 trajectories of at most 4.
    assert_eq!(
        report,
        ImportReport {
            episodes: 3,
            trajectories: 5,
            created: 4,
            replayed: 1,
            transitions: 16,
            split_episodes: 1,
            skipped_episodes: 0,
            // The interrupted run's trajectory first, found stored.
            trajectory_ids: vec![1, 2, 3, 4, 5],
        }
    );
    let stored = app.all_transitions(id).await;
    assert_eq!(stored.len(), steps.len());
    for (t, (_, s, a, n)) in stored.iter().zip(&steps) {
        assert_eq!(
            (vec2(&t["s"]), vec2(&t["a"]), vec2(&t["s_next"])),
            (*s, *a, *n)
        );
        // The model expects s + a; the robot moved 80 % of it.
        let expected = ((0.2 * a[0]).powi(2) + (0.2 * a[1]).powi(2)).sqrt();
        assert!(
            (t["deviation"].as_f64().unwrap() - expected).abs() < 1e-12,
            "{t}"
        );
    }
    let (_, page) = app.get_at(id, "runs").await;
    let mut sources: Vec<(i64, i64, usize)> = page["items"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| {
            assert_eq!(r["status"], "unsolicited");
            let s = &r["source"];
            assert_eq!(
                (s["dataset"].as_str(), s["label"].as_str()),
                (Some(dataset.as_str()), Some("bench"))
            );
            (
                s["episode"].as_i64().unwrap(),
                s["first_step"].as_i64().unwrap(),
                r["length"].as_u64().unwrap() as usize,
            )
        })
        .collect();
    sources.sort_unstable();
    assert_eq!(
        sources,
        [(0, 0, 4), (10, 0, 3), (20, 0, 4), (20, 4, 4), (20, 8, 1)]
    );

    // Run again: nothing new.
    let again = import(&app, id, &bench, &[&csv]).await.unwrap();
    assert_eq!(
        (again.created, again.replayed, again.trajectories),
        (0, 5, 5)
    );
    let (_, e) = app.get_at(id, "").await;
    assert_eq!(
        (e["n_trajectories"].as_i64(), e["n_transitions"].as_i64()),
        (Some(5), Some(16))
    );
    // Another label for the same episodes is another request: refused, named, nothing stored.
    let err = import(
        &app,
        id,
        &["--label", "other", "--max-transitions", "4"],
        &[&csv],
    )
    .await
    .unwrap_err();
    let text = format!("{err:#}");
    assert!(
        text.contains("imported before and differs now")
            && text.contains("409")
            && text.contains("source.label was \"bench\" and is now \"other\""),
        "{text}"
    );
    let (_, e) = app.get_at(id, "").await;
    assert_eq!(e["n_trajectories"], 5);
}

#[tokio::test]
async fn a_grown_or_fixed_file_imports_only_what_is_new_from_any_directory() {
    let (dir, db) = temp_db();
    let app = spawn_app(&db).await;
    let id = kinematic(&app).await;
    let csv = dir.path().join("log.csv");
    let steps = logged(&[3, 2, 4, 2]);
    // Two episodes and the first row of a third, then a bad line: the import stops there,
    // the two complete episodes stored.
    let mut text = String::from("episode,s_x,s_y,a_dx,a_dy,s_next_x,s_next_y\n");
    for (e, s, a, n) in &steps[..6] {
        text += &format!(
            "{e},{},{},{},{},{},{}\n",
            s[0], s[1], a[0], a[1], n[0], n[1]
        );
    }
    text += "20,0.1,0.1,oops,0,0.15,0.1\n";
    std::fs::write(&csv, &text).unwrap();
    let err = format!("{:#}", import(&app, id, &[], &[&csv]).await.unwrap_err());
    assert!(err.contains("oops"), "{err}");
    let (_, e) = app.get_at(id, "").await;
    assert_eq!(e["n_trajectories"], 2);

    // The line fixed and the log grown by two more episodes: only what is new is stored.
    write_csv(&csv, &steps);
    let report = import(&app, id, &[], &[&csv]).await.unwrap();
    assert_eq!((report.created, report.replayed), (2, 2), "{report:?}");
    // From another working directory, by another path to the same file: nothing new.
    let roundabout = dir.path().join(".").join("log.csv");
    let again = import(&app, id, &[], &[&roundabout]).await.unwrap();
    assert_eq!((again.created, again.replayed), (0, 4), "{again:?}");
    let (_, e) = app.get_at(id, "").await;
    assert_eq!(
        (e["n_trajectories"].as_i64(), e["n_transitions"].as_i64()),
        (Some(4), Some(11))
    );

    // An episode whose rows changed since it was stored: refused by name, nothing stored; the
    // episodes before it are recognised.
    let mut changed = steps.clone();
    changed[6].2[0] = 0.04;
    write_csv(&csv, &changed);
    let err = format!("{:#}", import(&app, id, &[], &[&csv]).await.unwrap_err());
    assert!(
        err.contains("episode 20 (from step 0)")
            && err.contains("transitions[1].a[0] was 0.05 and is now 0.04"),
        "{err}"
    );
    let (_, e) = app.get_at(id, "").await;
    assert_eq!(e["n_trajectories"], 4);
}

/// A LeRobot-style Parquet file: list columns `observation.state` and `action` (float32),
/// `episode_index` and `frame_index`, in two row groups with an episode across the boundary.
fn write_lerobot_parquet(path: &Path, episodes: &[Vec<[f32; 2]>], compression: Compression) {
    let list = |name: &str| {
        let element = Type::primitive_type_builder("element", Physical::FLOAT)
            .with_repetition(Repetition::OPTIONAL)
            .build()
            .unwrap();
        let repeated = Type::group_type_builder("list")
            .with_repetition(Repetition::REPEATED)
            .with_fields(vec![Arc::new(element)])
            .build()
            .unwrap();
        Arc::new(
            Type::group_type_builder(name)
                .with_repetition(Repetition::OPTIONAL)
                .with_converted_type(ConvertedType::LIST)
                .with_logical_type(Some(LogicalType::List))
                .with_fields(vec![Arc::new(repeated)])
                .build()
                .unwrap(),
        )
    };
    let int = |name: &str| {
        Arc::new(
            Type::primitive_type_builder(name, Physical::INT64)
                .with_repetition(Repetition::REQUIRED)
                .build()
                .unwrap(),
        )
    };
    let schema = Arc::new(
        Type::group_type_builder("schema")
            .with_fields(vec![
                list("observation.state"),
                list("action"),
                int("frame_index"),
                int("episode_index"),
            ])
            .build()
            .unwrap(),
    );
    let props = Arc::new(
        WriterProperties::builder()
            .set_compression(compression)
            .build(),
    );
    let mut writer =
        SerializedFileWriter::new(std::fs::File::create(path).unwrap(), schema, props).unwrap();
    // Frames: (episode, frame, state, action); the action of frame k moves to frame k + 1.
    let frames: Vec<(i64, i64, [f32; 2], [f32; 2])> = episodes
        .iter()
        .enumerate()
        .flat_map(|(e, states)| {
            states.iter().enumerate().map(move |(k, s)| {
                let next = states.get(k + 1).copied().unwrap_or(*s);
                (e as i64, k as i64, *s, [next[0] - s[0], next[1] - s[1]])
            })
        })
        .collect();
    let half = frames.len() / 2 + 1;
    for group in [&frames[..half], &frames[half..]] {
        let mut rg = writer.next_row_group().unwrap();
        let mut column = 0;
        while let Some(mut col) = rg.next_column().unwrap() {
            match col.untyped() {
                ColumnWriter::FloatColumnWriter(w) => {
                    let values: Vec<f32> = group
                        .iter()
                        .flat_map(|f| if column == 0 { f.2 } else { f.3 })
                        .collect();
                    let def = vec![3i16; values.len()];
                    let rep: Vec<i16> = (0..values.len()).map(|i| (i % 2) as i16).collect();
                    w.write_batch(&values, Some(&def), Some(&rep)).unwrap();
                }
                ColumnWriter::Int64ColumnWriter(w) => {
                    let values: Vec<i64> = group
                        .iter()
                        .map(|f| if column == 2 { f.1 } else { f.0 })
                        .collect();
                    w.write_batch(&values, None, None).unwrap();
                }
                _ => unreachable!(),
            }
            col.close().unwrap();
            column += 1;
        }
        rg.close().unwrap();
    }
    writer.close().unwrap();
}

#[tokio::test]
async fn a_lerobot_parquet_file_imports_frame_to_frame_per_episode() {
    let (dir, db) = temp_db();
    let app = spawn_app(&db).await;
    let id = kinematic(&app).await;
    let episodes: Vec<Vec<[f32; 2]>> = vec![
        (0..5).map(|k| [0.1 + 0.04 * k as f32, 0.3]).collect(),
        (0..4).map(|k| [0.5, 0.2 + 0.05 * k as f32]).collect(),
        vec![[0.9, 0.9]],
        (0..3)
            .map(|k| [1.0 + 0.02 * k as f32, 1.0 - 0.03 * k as f32])
            .collect(),
    ];
    for (name, compression) in [
        ("snappy.parquet", Compression::SNAPPY),
        ("zstd.parquet", Compression::ZSTD(Default::default())),
    ] {
        let path = dir.path().join(name);
        write_lerobot_parquet(&path, &episodes, compression);
        let before = app.all_transitions(id).await.len();
        let report = import(&app, id, &[], &[&path]).await.unwrap();
        assert_eq!(
            (report.episodes, report.created, report.transitions),
            (3, 3, 4 + 3 + 2),
            "{name}"
        );
        assert_eq!(
            report.skipped_episodes, 1,
            "the single-frame episode has no transition"
        );
        let stored = app.all_transitions(id).await;
        let new = &stored[before..];
        let expected: Vec<([f64; 2], [f64; 2], [f64; 2])> = episodes
            .iter()
            .flat_map(|states| {
                states.windows(2).map(|w| {
                    let f = |v: [f32; 2]| [f64::from(v[0]), f64::from(v[1])];
                    let a = [w[1][0] - w[0][0], w[1][1] - w[0][1]];
                    (f(w[0]), f(a), f(w[1]))
                })
            })
            .collect();
        assert_eq!(new.len(), expected.len());
        for (t, (s, a, n)) in new.iter().zip(&expected) {
            assert_eq!(
                (vec2(&t["s"]), vec2(&t["a"]), vec2(&t["s_next"])),
                (*s, *a, *n),
                "{name}"
            );
            assert!(t["deviation"].as_f64().unwrap() >= 0.0);
        }
        let again = import(&app, id, &[], &[&path]).await.unwrap();
        assert_eq!((again.created, again.replayed), (0, 3), "{name}");
    }
    let (_, e) = app.get_at(id, "").await;
    assert_eq!(e["n_trajectories"], 6);
}

#[tokio::test]
async fn bad_input_is_named_and_stops_the_import() {
    let (dir, db) = temp_db();
    let app = spawn_app(&db).await;
    let id = kinematic(&app).await;
    let bad = dir.path().join("bad.csv");
    std::fs::write(
        &bad,
        "episode,s_x,s_y,a_dx,a_dy,s_next_x,s_next_y\n0,0.1,0.1,0.05,0,0.15,0.1\n1,0.1,0.1,oops,0,0.15,0.1\n",
    )
    .unwrap();
    let text = format!("{:#}", import(&app, id, &[], &[&bad]).await.unwrap_err());
    assert!(
        text.contains("line 3") && text.contains("a_dx: expected a number, got \"oops\""),
        "{text}"
    );

    let unsorted = dir.path().join("unsorted.csv");
    write_csv(
        &unsorted,
        &[logged(&[2])[..].to_vec(), logged(&[1, 1]), logged(&[2])].concat(),
    );
    let text = format!(
        "{:#}",
        import(&app, id, &[], &[&unsorted]).await.unwrap_err()
    );
    assert!(text.contains("episode 0 appears again"), "{text}");

    let wrong = dir.path().join("wrong.csv");
    std::fs::write(&wrong, "x,y,z\n1,2,3\n").unwrap();
    let text = format!("{:#}", import(&app, id, &[], &[&wrong]).await.unwrap_err());
    assert!(
        text.contains("no state columns") && text.contains("x, y, z"),
        "{text}"
    );
    // Outside the experiment's state space: the server's 422, with the field.
    let outside = dir.path().join("outside.csv");
    write_csv(&outside, &[(0, [5.0, 0.1], [0.05, 0.0], [5.05, 0.1])]);
    let text = format!(
        "{:#}",
        import(&app, id, &[], &[&outside]).await.unwrap_err()
    );
    assert!(
        text.contains("422 validation_failed") && text.contains("transitions[0].s"),
        "{text}"
    );
    let missing = dir.path().join("missing.csv");
    let text = format!(
        "{:#}",
        import(&app, id, &[], &[&missing]).await.unwrap_err()
    );
    assert!(text.contains("missing.csv"), "{text}");
    let text = format!("{:#}", import(&app, 99, &[], &[&bad]).await.unwrap_err());
    assert!(text.contains("404 not_found"), "{text}");
}

/// `POST …/imports` with `body` (a file) under `content_type` and the query `query`.
async fn upload(
    app: &TestApp,
    id: i64,
    query: &[(&str, &str)],
    content_type: &str,
    body: Vec<u8>,
) -> (u16, Value) {
    let r = app
        .client
        .post(app.url(&format!("/v1/experiments/{id}/imports")))
        .query(query)
        .header("content-type", content_type)
        .body(body)
        .send()
        .await
        .unwrap();
    let status = r.status().as_u16();
    (status, r.json().await.unwrap())
}

#[tokio::test]
async fn the_import_route_stores_what_the_command_line_would_and_either_finds_the_others() {
    let (dir, db) = temp_db();
    let app = spawn_app(&db).await;
    let id = kinematic(&app).await;
    let steps = logged(&[4, 3, 9]);
    let csv = dir.path().join("pushes.csv");
    write_csv(&csv, &steps);
    let dataset = precond_tools::import::default_dataset_name(&csv);
    let query = [("dataset", dataset.as_str()), ("label", "bench")];

    let (status, report) = upload(&app, id, &query, "text/csv", std::fs::read(&csv).unwrap()).await;
    assert_eq!(status, 200, "{report}");
    let report: ImportReport = serde_json::from_value(report).unwrap();
    assert_eq!(
        report,
        ImportReport {
            episodes: 3,
            trajectories: 3,
            created: 3,
            replayed: 0,
            transitions: 16,
            split_episodes: 0,
            skipped_episodes: 0,
            trajectory_ids: vec![1, 2, 3],
        }
    );
    // The command line, on the same file with the same label, finds every episode stored.
    let again = import(&app, id, &["--label", "bench"], &[&csv])
        .await
        .unwrap();
    assert_eq!((again.created, again.replayed), (0, 3));
    assert_eq!(again.trajectory_ids, report.trajectory_ids);
    // The stored trajectories carry their source, and the labels the experiment's model gave.
    let t: Value = app
        .client
        .get(app.url(&format!("/v1/experiments/{id}/transitions")))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(t["items"].as_array().unwrap().len(), 16);
    let run: Value = app
        .client
        .get(app.url(&format!("/v1/experiments/{id}/runs")))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert!(
        run["items"]
            .as_array()
            .unwrap()
            .iter()
            .all(|r| r["source"]["dataset"] == dataset.as_str() && r["source"]["label"] == "bench"),
        "{run}"
    );

    // A changed episode is refused by name, saying what was stored before it.
    let mut changed = steps.clone();
    changed[5].3[0] += 0.01; // episode 10's second step
    let other = dir.path().join("changed.csv");
    write_csv(&other, &changed);
    let (status, e) = upload(&app, id, &query, "text/csv", std::fs::read(&other).unwrap()).await;
    assert_eq!(status, 409, "{e}");
    let message = e["error"]["message"].as_str().unwrap();
    assert!(
        message.contains("the import stopped at episode 10 from step 0")
            && message.contains("1 of its trajectories were stored before"),
        "{message}"
    );
    // The same as data, beside the refusal's own details.
    let details = &e["error"]["details"];
    assert_eq!(details["field"], "transitions[1].s_next[0]", "{e}");
    assert_eq!(
        (
            &details["import"]["episode"],
            &details["import"]["first_step"]
        ),
        (&json!(10), &json!(0)),
        "{e}"
    );
    let before: ImportReport =
        serde_json::from_value(details["import"]["stored_before"].clone()).unwrap();
    assert_eq!(
        (before.trajectories, before.replayed, before.trajectory_ids),
        (1, 1, vec![1])
    );

    // Fewer transitions per trajectory than the server's limit, as the command line's
    // --max-transitions: the 9-step episode becomes 4 + 4 + 1.
    let split = [("dataset", "split"), ("max_transitions", "4")];
    let (status, report) = upload(&app, id, &split, "text/csv", std::fs::read(&csv).unwrap()).await;
    assert_eq!(status, 200, "{report}");
    let report: ImportReport = serde_json::from_value(report).unwrap();
    assert_eq!(
        (report.episodes, report.trajectories, report.split_episodes),
        (3, 5, 1)
    );
}

#[tokio::test]
async fn the_import_route_names_bad_files_and_bad_requests() {
    let (_dir, db) = temp_db();
    let app = spawn_app_with(
        &db,
        precond::http::HttpConfig {
            max_import_bytes: 200,
            ..precond::http::HttpConfig::default()
        },
    )
    .await;
    let id = kinematic(&app).await;
    let q = [("dataset", "logs")];
    // A missing column, named with what the file has and the query parameter to name it with.
    let (status, e) = upload(&app, id, &q, "text/csv", b"px,py\n1,2\n".to_vec()).await;
    assert_eq!(status, 422, "{e}");
    assert_eq!(e["error"]["details"]["field"], "body");
    let reason = e["error"]["details"]["reason"].as_str().unwrap();
    assert!(
        reason.contains("no state columns")
            && reason.contains("px, py")
            && reason.contains("with state"),
        "{reason}"
    );
    // A bad value, by line and column.
    let bad = b"s_x,s_y,a_dx,a_dy,s_next_x,s_next_y\n0.1,0.2,0.05,0,0.15,0.2\n0.1,oops,0,0,0,0\n";
    let (status, e) = upload(&app, id, &q, "text/csv", bad.to_vec()).await;
    assert_eq!(status, 422, "{e}");
    let message = e["error"]["message"].as_str().unwrap();
    assert!(
        message.contains("line 3") && message.contains("0 of its trajectories were stored before"),
        "{message}"
    );
    let stop = &e["error"]["details"]["import"];
    assert_eq!(
        (&stop["episode"], &stop["stored_before"]["trajectories"]),
        (&Value::Null, &json!(0)),
        "{e}"
    );
    // The names every trajectory's source needs, checked before the file is read: a label
    // too long, a dataset id that cannot be part of a key — named as the query calls them.
    let long = "x".repeat(1001);
    for (query, field) in [
        ([("dataset", "logs"), ("label", long.as_str())], "label"),
        (
            [("dataset", "logs"), ("dataset_id", "no spaces")],
            "dataset_id",
        ),
    ] {
        let (status, e) = upload(&app, id, &query, "text/csv", vec![b'1'; 1000]).await;
        assert_eq!(
            (status, e["error"]["details"]["field"].as_str()),
            (422, Some(field)),
            "{e}"
        );
    }
    // Transitions per trajectory within 1 and the server's limit, named.
    let zero = [("dataset", "logs"), ("max_transitions", "0")];
    let (status, e) = upload(&app, id, &zero, "text/csv", bad.to_vec()).await;
    assert_eq!(
        (status, e["error"]["details"]["field"].as_str()),
        (422, Some("max_transitions"))
    );
    // Not a file type: 415; octet-stream without `format`: 422 naming it; too large: 413.
    let (status, _) = upload(&app, id, &q, "text/plain", b"x\n".to_vec()).await;
    assert_eq!(status, 415);
    let (status, e) = upload(&app, id, &q, "application/octet-stream", b"x\n".to_vec()).await;
    assert_eq!(
        (status, e["error"]["details"]["field"].as_str()),
        (422, Some("format"))
    );
    let (status, e) = upload(&app, id, &q, "text/csv", vec![b'1'; 1000]).await;
    assert_eq!(
        (status, e["error"]["code"].as_str()),
        (413, Some("payload_too_large"))
    );
    // No experiment: 404 before anything is read; no dataset: 422.
    let (status, _) = upload(&app, 999, &q, "text/csv", b"x\n".to_vec()).await;
    assert_eq!(status, 404);
    let (status, _) = upload(&app, id, &[], "text/csv", b"x\n".to_vec()).await;
    assert_eq!(status, 422);
    // Nothing of these was stored.
    let t: Value = app
        .client
        .get(app.url(&format!("/v1/experiments/{id}/transitions")))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(t["items"].as_array().unwrap().len(), 0);
}
