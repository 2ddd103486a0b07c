-- As SQLite's 0024: custom experiments created before `domain.features.prediction` and
-- `move_length` existed fed the MDE no prediction; their stored settings say so.
UPDATE experiments
SET settings = jsonb_set(settings::jsonb, '{domain,features,prediction}', '[]'::jsonb)::text
WHERE (settings::jsonb -> 'domain' ->> 'kind') = 'custom'
  AND jsonb_typeof(settings::jsonb -> 'domain' -> 'features') = 'object'
  AND (settings::jsonb -> 'domain' -> 'features' -> 'prediction') IS NULL;
UPDATE experiments
SET settings = jsonb_set(settings::jsonb, '{domain,features,move_length}', 'false'::jsonb)::text
WHERE (settings::jsonb -> 'domain' ->> 'kind') = 'custom'
  AND jsonb_typeof(settings::jsonb -> 'domain' -> 'features') = 'object'
  AND (settings::jsonb -> 'domain' -> 'features' -> 'move_length') IS NULL;
