-- Experiments created before `learning.acquisition` existed scored candidates with the paper's
-- lower confidence bound: complete their stored settings with it (see 0007 for why rows are
-- completed here rather than read with fallbacks).
UPDATE experiments SET settings = json_set(settings, '$.learning.acquisition', 'lcb')
WHERE json_type(settings, '$.learning.acquisition') IS NULL;
