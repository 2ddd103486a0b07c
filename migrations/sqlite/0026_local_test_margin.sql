-- `learning.local_test_margin`: test plans and default judgements judge each state-action at
-- its locally calibrated β. Experiments created before it existed judged every state-action at
-- the test β: complete their stored settings with false (see 0007 for why rows are completed
-- here rather than read with fallbacks). The margin itself is not stored: a version rebuilds
-- it from its training set.
UPDATE experiments SET settings = json_set(settings, '$.learning.local_test_margin', json('false'))
WHERE json_type(settings, '$.learning.local_test_margin') IS NULL;
