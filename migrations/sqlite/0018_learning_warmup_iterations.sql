-- `learning.warmup_iterations`: `active` answers its first iterations with random rollouts.
-- Experiments created before it existed chose every `active` trajectory by the acquisition:
-- complete their stored settings with 0 (see 0007 for why rows are completed here rather than
-- read with fallbacks).
UPDATE experiments SET settings = json_set(settings, '$.learning.warmup_iterations', 0)
WHERE json_type(settings, '$.learning.warmup_iterations') IS NULL;
