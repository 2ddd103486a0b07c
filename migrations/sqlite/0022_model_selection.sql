-- Warm refits: how each version's kernel and label cap were chosen (anew, or kept from an
-- earlier version) and what its fit spent its time on, as JSON (`mde::SelectionRecord`).
-- Versions fitted before have none. Experiments created before `mde.reselect_every` existed
-- chose anew at every fit: their stored settings are completed with 1 (see 0007 for why rows
-- are completed here rather than read with fallbacks).
ALTER TABLE models ADD COLUMN selection TEXT;
UPDATE experiments SET settings = json_set(settings, '$.mde.reselect_every', 1)
WHERE json_type(settings, '$.mde.reselect_every') IS NULL;
