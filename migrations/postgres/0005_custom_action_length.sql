-- Custom experiments created before `domain.features.action_length` existed fed the MDE the
-- listed components only: complete their stored settings with `false`, as SQLite's 0017 does
-- (settings are JSON text).
UPDATE experiments
SET settings = jsonb_set(settings::jsonb, '{domain,features,action_length}', 'false'::jsonb)::text
WHERE (settings::jsonb -> 'domain' ->> 'kind') = 'custom'
  AND jsonb_typeof(settings::jsonb -> 'domain' -> 'features') = 'object'
  AND (settings::jsonb -> 'domain' -> 'features' -> 'action_length') IS NULL;
