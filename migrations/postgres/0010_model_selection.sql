-- As SQLite's 0022: each version's selection record, and `mde.reselect_every` completed with 1
-- for experiments created before it existed (they chose anew at every fit).
ALTER TABLE models ADD COLUMN selection TEXT;
UPDATE experiments
SET settings = jsonb_set(settings::jsonb, '{mde,reselect_every}', '1'::jsonb)::text
WHERE (settings::jsonb -> 'mde' -> 'reselect_every') IS NULL;
