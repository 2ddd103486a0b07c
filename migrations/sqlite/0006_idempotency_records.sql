-- An idempotency record keeps what the first ingest under its key did — the trajectory it
-- stored, the model version that answered and the experiment's trajectory count then — rather
-- than an HTTP answer: the service rebuilds the same answer from these values and the stored
-- trajectory (its labels are in `transitions`). Rows kept before take the values from the
-- answer they stored.
--
-- `response` stays readable for tools that inspect the table: a JSON object of those values
-- (with the trajectory's identifier as `id`, as in the answer), computed, never written.
CREATE TABLE idempotency_records (
    experiment_id   INTEGER NOT NULL REFERENCES experiments (id),
    key             TEXT    NOT NULL,
    request         TEXT    NOT NULL,
    trajectory_id   INTEGER NOT NULL REFERENCES trajectories (id),
    model_version   INTEGER NOT NULL,
    n_trajectories  INTEGER NOT NULL,
    created_at      TEXT    NOT NULL,
    response        TEXT GENERATED ALWAYS AS (json_object(
                        'id', trajectory_id,
                        'model_version', model_version,
                        'n_trajectories', n_trajectories)) VIRTUAL,
    PRIMARY KEY (experiment_id, key)
);

INSERT INTO idempotency_records
    (experiment_id, key, request, trajectory_id, model_version, n_trajectories, created_at)
SELECT k.experiment_id, k.key, k.request,
       json_extract(k.response, '$.id'),
       COALESCE(json_extract(k.response, '$.model_version'), 0),
       COALESCE(json_extract(k.response, '$.n_trajectories'),
                (SELECT COUNT(*) FROM trajectories t
                 WHERE t.experiment_id = k.experiment_id
                   AND t.id <= json_extract(k.response, '$.id'))),
       k.created_at
FROM idempotency_keys k;

DROP TABLE idempotency_keys;
ALTER TABLE idempotency_records RENAME TO idempotency_keys;
