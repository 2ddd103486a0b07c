-- Custom experiments created before `domain.features.action_length` existed fed the MDE the
-- listed components only: complete their stored settings with `false`, so that their stored
-- model versions (fitted on those features) keep serving (see 0007 for why rows are completed
-- here rather than read with fallbacks).
UPDATE experiments SET settings = json_set(settings, '$.domain.features.action_length', json('false'))
WHERE json_extract(settings, '$.domain.kind') = 'custom'
  AND json_type(settings, '$.domain.features') = 'object'
  AND json_type(settings, '$.domain.features.action_length') IS NULL;
