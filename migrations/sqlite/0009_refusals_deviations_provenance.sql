-- Three things a robotics stack needs to see in the store:
--
-- 1. Refused proposals. A proposal request answered `422 no_plan` (no goal-reaching trajectory
--    inside the precondition at any β tried) used to leave no trace; each is now one row: the
--    problem, the client, the learning state that shaped it, every β tried (in order, JSON) and
--    the extensions spent. `candidates` is how many of the client's own candidates were judged
--    (NULL when the service planned).
-- 2. Deviating executions. A trajectory posted for a proposal whose actions are not the
--    proposal's (element-wise, relative tolerance 1e-6), that is longer than the proposal, or
--    that starts elsewhere than the proposal's start, is flagged `deviating` (a prefix of the
--    proposal is not). Trajectories stored before are checked here, once, by the same rule.
-- 3. Provenance. A trajectory may say where it comes from (an imported log, a Gymnasium
--    environment): the source dataset or file, the episode in it, the step of the episode its
--    first transition was (an episode longer than one post allows is split), a free-form label.

CREATE TABLE refusals (
    id             INTEGER PRIMARY KEY,
    experiment_id  INTEGER NOT NULL REFERENCES experiments (id),
    client_id      TEXT,
    iteration      INTEGER NOT NULL,
    strategy       TEXT    NOT NULL,
    model_version  INTEGER NOT NULL,
    start          TEXT    NOT NULL,
    goal           TEXT    NOT NULL,
    betas          TEXT    NOT NULL,
    extensions     INTEGER NOT NULL CHECK (extensions >= 0),
    candidates     INTEGER,
    created_at     TEXT    NOT NULL
);
CREATE INDEX refusals_by_experiment ON refusals (experiment_id, iteration);

ALTER TABLE trajectories ADD COLUMN deviating INTEGER NOT NULL DEFAULT 0
    CHECK (deviating IN (0, 1));
ALTER TABLE trajectories ADD COLUMN source_dataset TEXT;
ALTER TABLE trajectories ADD COLUMN source_episode INTEGER;
ALTER TABLE trajectories ADD COLUMN source_first_step INTEGER;
ALTER TABLE trajectories ADD COLUMN source_label TEXT;

-- The rule of src/service/ingest.rs (`deviates`), for the trajectories stored before it existed.
UPDATE trajectories SET deviating = 1
WHERE proposal_id IS NOT NULL
  AND EXISTS (
    SELECT 1 FROM proposals p
    WHERE p.id = trajectories.proposal_id
      AND (trajectories.n_transitions > json_array_length(p.body, '$.trajectory.actions')
           OR EXISTS (
               SELECT 1 FROM transitions x, json_each(x.a) e
               WHERE x.trajectory_id = trajectories.id
                 AND abs(e.value - json_extract(p.body,
                         printf('$.trajectory.actions[%d][%d]', x.step, e.key)))
                     > 1e-6 * max(1.0, abs(json_extract(p.body,
                         printf('$.trajectory.actions[%d][%d]', x.step, e.key)))))
           OR EXISTS (
               SELECT 1 FROM transitions x, json_each(x.s) e
               WHERE x.trajectory_id = trajectories.id AND x.step = 0
                 AND abs(e.value - json_extract(p.start, printf('$[%d]', e.key)))
                     > 1e-6 * max(1.0, abs(json_extract(p.start, printf('$[%d]', e.key)))))));
