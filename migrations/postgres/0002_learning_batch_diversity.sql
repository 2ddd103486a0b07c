-- Experiments created before `learning.batch_diversity` existed chose every trajectory of a
-- batch from the fitted model alone: complete their stored settings with false, as SQLite's
-- 0014 does (settings are JSON text).
UPDATE experiments
SET settings = jsonb_set(settings::jsonb, '{learning,batch_diversity}', 'false'::jsonb)::text
WHERE (settings::jsonb -> 'learning' -> 'batch_diversity') IS NULL;
