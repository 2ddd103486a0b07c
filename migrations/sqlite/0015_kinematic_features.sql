-- Kinematic experiments created before `domain.features` existed fed the MDE the state and the
-- action only: complete their stored settings with `state_action`, so that their stored model
-- versions (fitted on those features) keep serving (see 0007 for why rows are completed here
-- rather than read with fallbacks).
UPDATE experiments SET settings = json_set(settings, '$.domain.features', 'state_action')
WHERE json_extract(settings, '$.domain.kind') = 'kinematic'
  AND json_type(settings, '$.domain.features') IS NULL;
