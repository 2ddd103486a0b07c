-- As SQLite's 0023: why each proposal request was refused (`no_plan` or `deadline_exceeded`).
ALTER TABLE refusals ADD COLUMN reason TEXT NOT NULL DEFAULT 'no_plan';
