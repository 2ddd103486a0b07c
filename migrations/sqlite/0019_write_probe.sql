-- Readiness probes a write here while writes fail for lack of space: one row of random text
-- replaced in one transaction, so the probe allocates pages as an ingest does (a full disk is
-- reported until such a write succeeds again).
CREATE TABLE write_probe (
    id INTEGER PRIMARY KEY,
    written_at TEXT NOT NULL,
    padding TEXT NOT NULL
);
