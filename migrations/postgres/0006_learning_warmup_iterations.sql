-- `learning.warmup_iterations`, as SQLite's 0018 does: experiments created before it existed
-- chose every `active` trajectory by the acquisition (0).
UPDATE experiments
SET settings = jsonb_set(settings::jsonb, '{learning,warmup_iterations}', '0'::jsonb)::text
WHERE (settings::jsonb -> 'learning' -> 'warmup_iterations') IS NULL;
