-- Custom experiments created before `domain.features.prediction` and `move_length` existed fed
-- the MDE the state, the action and the action's length only: complete their stored settings
-- with none, so that their stored model versions (fitted on those features) keep serving (see
-- 0007 for why rows are completed here rather than read with fallbacks).
UPDATE experiments SET settings = json_set(settings, '$.domain.features.prediction', json('[]'))
WHERE json_extract(settings, '$.domain.kind') = 'custom'
  AND json_type(settings, '$.domain.features') = 'object'
  AND json_type(settings, '$.domain.features.prediction') IS NULL;
UPDATE experiments SET settings = json_set(settings, '$.domain.features.move_length', json('false'))
WHERE json_extract(settings, '$.domain.kind') = 'custom'
  AND json_type(settings, '$.domain.features') = 'object'
  AND json_type(settings, '$.domain.features.move_length') IS NULL;
