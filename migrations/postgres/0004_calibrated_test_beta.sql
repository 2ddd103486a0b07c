-- `learning.calibrate_test_beta` and each version's certified test β, as SQLite's 0016 does:
-- experiments created before planned at `learning.test_beta` itself (false); versions fitted
-- before made no choice (null).
UPDATE experiments
SET settings = jsonb_set(settings::jsonb, '{learning,calibrate_test_beta}', 'false'::jsonb)::text
WHERE (settings::jsonb -> 'learning' -> 'calibrate_test_beta') IS NULL;
ALTER TABLE models ADD COLUMN beta_choice TEXT NOT NULL DEFAULT 'null';
