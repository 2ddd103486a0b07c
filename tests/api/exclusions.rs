//! Exclusions: a trajectory or a time range left out of an experiment's model, audited, and
//! restored; each version is rebuilt on exactly the data it was fitted on.

use crate::helpers::*;
use serde_json::{Value, json};

/// An experiment whose model is fitted only when asked (a batch never completes).
fn manual_fits() -> Value {
    json!({"mde": {"restarts": 0}, "learning": {"batch_size": 1000}})
}

/// A trajectory the model gets wrong: the moves right from (3, y) stay put.
fn stuck_trajectory(y: i64, n: i64) -> Value {
    let transitions: Vec<Value> = (0..n)
        .map(|_| json!({"s": [3, y], "a": [1, 0], "s_next": [3, y]}))
        .collect();
    json!({ "transitions": transitions })
}

/// Waits for a version newer than `after` and returns it.
async fn next_version(app: &TestApp, id: i64, after: i64) -> Value {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(600);
    loop {
        let (_, model) = app.get_at(id, "model").await;
        if model["version"].as_i64() > Some(after) {
            return model;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "no version after {after}"
        );
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
}

async fn judged_at_the_bad_move(app: &TestApp, id: i64) -> Value {
    let (status, judged) = app
        .post_at(
            id,
            "precondition",
            &json!({"points": [{"s": [3, 5], "a": [1, 0]}], "beta": 0}),
        )
        .await;
    assert_eq!(status, 200, "{judged}");
    judged["results"][0].clone()
}

#[tokio::test]
async fn an_excluded_trajectory_is_left_out_of_the_next_fit_kept_out_across_a_restart_and_restored()
{
    let (_dir, app, id) = fresh_experiment(manual_fits()).await;
    app.store_trajectory(id, &free_row_trajectory(0, 0, 3))
        .await;
    let bad = app.store_trajectory(id, &stuck_trajectory(5, 4)).await;
    app.store_trajectory(id, &free_row_trajectory(0, 2, 2))
        .await;
    let bad_id = bad["id"].as_i64().unwrap();
    let all = app.refit(id).await;
    assert_eq!(all["n_train"], json!(9));
    assert_eq!(all["exclusions"], json!([]));
    let wrong_before = judged_at_the_bad_move(&app, id).await;

    let (status, made) = app
        .post_at(
            id,
            "exclusions",
            &json!({"trajectory_id": bad_id, "reason": "the cart was blocked by a cable"}),
        )
        .await;
    assert_eq!(status, 201, "{made}");
    assert_eq!(made["status"], json!("in_effect"));
    assert_eq!(made["trajectory_ids"], json!([bad_id]));
    assert_eq!(made["n_transitions"], json!(4));
    assert_eq!(made["reason"], json!("the cart was blocked by a cable"));
    assert_eq!(made["created_by"], Value::Null, "no tokens: nobody to name");
    let exclusion = made["id"].as_i64().unwrap();

    // The refit it requested runs without being asked, and leaves the trajectory out.
    let without = next_version(&app, id, all["version"].as_i64().unwrap()).await;
    assert_eq!(without["n_train"], json!(5));
    assert_eq!(without["exclusions"], json!([exclusion]));
    let wrong_without = judged_at_the_bad_move(&app, id).await;
    assert!(
        wrong_without["mu"].as_f64().unwrap() < wrong_before["mu"].as_f64().unwrap() - 0.1,
        "without the stuck moves the model no longer expects them to deviate: \
         {wrong_before} then {wrong_without}"
    );
    let (_, listed) = app.get_at(id, "exclusions").await;
    assert_eq!(listed["total"], json!(1));
    assert_eq!(listed["items"][0]["applied"], json!(true));
    let (_, runs) = app.get_at(id, "runs").await;
    let excluded: Vec<(i64, Value)> = runs["items"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| {
            (
                r["trajectory_id"].as_i64().unwrap(),
                r["excluded_by"].clone(),
            )
        })
        .collect();
    for (t, by) in excluded {
        let expected = if t == bad_id {
            json!(exclusion)
        } else {
            Value::Null
        };
        assert_eq!(by, expected, "trajectory {t}");
    }
    // Still stored: listed, exported, counted.
    assert_eq!(app.all_transitions(id).await.len(), 9);

    // A restart rebuilds the version on the transitions it was fitted on.
    let app = app.restart().await;
    let (_, again) = app.get_at(id, "model").await;
    assert_eq!(again["version"], without["version"]);
    assert_eq!(again["exclusions"], json!([exclusion]));
    assert_eq!(judged_at_the_bad_move(&app, id).await, wrong_without);

    let (status, restored) = app
        .post_at(id, &format!("exclusions/{exclusion}/restore"), &json!({}))
        .await;
    assert_eq!(status, 200, "{restored}");
    assert_eq!(restored["status"], json!("restored"));
    assert!(restored["restored_at"].is_string());
    let with = next_version(&app, id, without["version"].as_i64().unwrap()).await;
    assert_eq!(with["n_train"], json!(9));
    assert_eq!(with["exclusions"], json!([]));
    // Restoring twice changes nothing and requests no fit.
    let (status, twice) = app
        .post_at(id, &format!("exclusions/{exclusion}/restore"), &json!({}))
        .await;
    assert_eq!(status, 200);
    assert_eq!(twice["restored_at"], restored["restored_at"]);
    assert_eq!(twice["applied"], json!(true));
    let (_, runs) = app.get_at(id, "runs").await;
    assert!(
        runs["items"]
            .as_array()
            .unwrap()
            .iter()
            .all(|r| r["excluded_by"].is_null())
    );
}

#[tokio::test]
async fn a_time_range_covers_the_trajectories_stored_in_it_and_bad_requests_store_nothing() {
    let (_dir, app, id) = fresh_experiment(manual_fits()).await;
    app.store_trajectory(id, &free_row_trajectory(0, 0, 2))
        .await;
    tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    let later = app.store_trajectory(id, &stuck_trajectory(5, 2)).await;
    let also = app.store_trajectory(id, &stuck_trajectory(6, 3)).await;
    let from = later["created_at"].as_str().unwrap().to_string();
    let to = "2999-01-01T00:00:00Z";

    let (status, made) = app
        .post_at(
            id,
            "exclusions",
            &json!({"since": from, "until": to, "reason": "calibration day"}),
        )
        .await;
    assert_eq!(status, 201, "{made}");
    assert_eq!(made["trajectory_ids"], json!([later["id"], also["id"]]));
    assert_eq!(made["n_transitions"], json!(5));
    assert_eq!(made["trajectory_id"], Value::Null);
    assert_eq!(
        made["applied"],
        json!(false),
        "no version was fitted under it yet"
    );
    let model = next_version(&app, id, 0).await;
    assert_eq!(model["n_train"], json!(2));
    // The range never grows: a trajectory stored after the exclusion is in the next fit.
    app.store_trajectory(id, &free_row_trajectory(0, 1, 3))
        .await;
    assert_eq!(app.refit(id).await["n_train"], json!(5));

    let bad: [(Value, &str); 9] = [
        (json!({"reason": "x"}), "trajectory_id"),
        (
            json!({"trajectory_id": 1, "since": from, "until": to, "reason": "x"}),
            "trajectory_id",
        ),
        (json!({"since": from, "reason": "x"}), "until"),
        (json!({"until": to, "reason": "x"}), "since"),
        (
            json!({"since": "yesterday", "until": to, "reason": "x"}),
            "since",
        ),
        (json!({"since": to, "until": from, "reason": "x"}), "until"),
        (json!({"trajectory_id": 99, "reason": "x"}), "trajectory_id"),
        (json!({"trajectory_id": 1, "reason": ""}), "reason"),
        (
            json!({"since": "2999-01-01T00:00:00Z", "until": "2999-01-02T00:00:00Z", "reason": "x"}),
            "since",
        ),
    ];
    for (body, field) in bad {
        let (status, answer) = app.post_at(id, "exclusions", &body).await;
        assert_eq!(status, 422, "{body}: {answer}");
        assert_eq!(
            answer["error"]["details"]["field"],
            json!(field),
            "{body}: {answer}"
        );
    }
    let (status, answer) = app
        .post_at(
            id,
            "exclusions",
            &json!({"trajectory_id": 1, "reason": "bell\u{7}"}),
        )
        .await;
    assert_eq!((status, code(&answer)), (422, "validation_failed"));
    // Everything left would be excluded: refused, nothing stored.
    let (status, answer) = app
        .post_at(
            id,
            "exclusions",
            &json!({"since": "2000-01-01T00:00:00Z", "until": to, "reason": "everything"}),
        )
        .await;
    assert_eq!(status, 409, "{answer}");
    let (status, answer) = app.post_at(id, "exclusions/99/restore", &json!({})).await;
    assert_eq!(status, 404, "{answer}");
    let (_, listed) = app.get_at(id, "exclusions").await;
    assert_eq!(
        listed["total"],
        json!(1),
        "only the first exclusion is stored: {listed}"
    );
}
