-- As SQLite's 0026: experiments created before `learning.local_test_margin` existed judged
-- every state-action at the test β (false).
UPDATE experiments
SET settings = jsonb_set(settings::jsonb, '{learning,local_test_margin}', 'false'::jsonb)::text
WHERE (settings::jsonb -> 'learning' -> 'local_test_margin') IS NULL;
