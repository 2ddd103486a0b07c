-- `learning.calibrate_test_beta`: test plans use the β each fitted version certifies on its own
-- training state-actions held out (at most `learning.test_beta`). Experiments created before it
-- existed planned at `learning.test_beta` itself: complete their stored settings with false
-- (see 0007 for why rows are completed here rather than read with fallbacks). Each version
-- keeps its choice (JSON: {beta, safe, unsafe_transitions, trusted_safe, trusted_unsafe}, or
-- null where none was made, as for every version fitted before).
UPDATE experiments SET settings = json_set(settings, '$.learning.calibrate_test_beta', json('false'))
WHERE json_type(settings, '$.learning.calibrate_test_beta') IS NULL;
ALTER TABLE models ADD COLUMN beta_choice TEXT NOT NULL DEFAULT 'null';
