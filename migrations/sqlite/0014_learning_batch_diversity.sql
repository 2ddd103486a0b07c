-- Experiments created before `learning.batch_diversity` existed chose every trajectory of a
-- batch from the fitted model alone: complete their stored settings with false (see 0007 for
-- why rows are completed here rather than read with fallbacks).
UPDATE experiments SET settings = json_set(settings, '$.learning.batch_diversity', json('false'))
WHERE json_type(settings, '$.learning.batch_diversity') IS NULL;
