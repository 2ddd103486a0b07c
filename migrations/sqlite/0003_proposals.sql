-- Proposals: the trajectory the service asked a client to execute, with the candidates it was
-- chosen from. A proposal is a lease: `open` until its trajectory is posted (`executed`), the
-- client abandons it (`abandoned`) or `expires_at` passes (`expired`).
CREATE TABLE proposals (
    id             INTEGER PRIMARY KEY,
    experiment_id  INTEGER NOT NULL REFERENCES experiments (id),
    client_id      TEXT,
    status         TEXT    NOT NULL CHECK (status IN ('open', 'executed', 'abandoned', 'expired')),
    iteration      INTEGER NOT NULL,
    beta           REAL    NOT NULL,
    strategy       TEXT    NOT NULL,
    model_version  INTEGER NOT NULL,
    start          TEXT    NOT NULL,
    goal           TEXT    NOT NULL,
    body           TEXT    NOT NULL,
    created_at     TEXT    NOT NULL,
    expires_at     TEXT    NOT NULL,
    -- expires_at as Unix seconds, for comparisons.
    expires_unix   REAL    NOT NULL
);
CREATE INDEX proposals_by_client ON proposals (experiment_id, client_id, status);
