-- Kinematic experiments created before `domain.features` existed fed the MDE the state and the
-- action only: complete their stored settings with `state_action`, as SQLite's 0015 does
-- (settings are JSON text).
UPDATE experiments
SET settings = jsonb_set(settings::jsonb, '{domain,features}', '"state_action"'::jsonb)::text
WHERE (settings::jsonb -> 'domain' ->> 'kind') = 'kinematic'
  AND (settings::jsonb -> 'domain' -> 'features') IS NULL;
