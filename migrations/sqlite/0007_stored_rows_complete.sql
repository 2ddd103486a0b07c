-- Rows written before a setting or a recorded value existed get, once and here, the value they
-- were used with, so the code reads every stored row as complete (no "stored before X existed"
-- fallbacks in the code):
-- - experiments fitted the smooth Matérn 5/2 kernel before `mde.kernel` existed, raw labels before
--   `mde.label_cap` existed, and never relaxed β before `learning.relax_beta` existed;
-- - model versions fitted before kernels were recorded used Matérn 5/2 (main GP and noise GP);
-- - versions fitted before caps were recorded used the experiment's one fixed cap, and judged no
--   candidates; judgements stored before groups were used left one transition out (0 groups).

UPDATE experiments SET settings = json_set(settings, '$.mde.kernel', 'matern52')
WHERE json_type(settings, '$.mde.kernel') IS NULL;

UPDATE experiments SET settings = json_set(settings, '$.mde.label_cap', 0)
WHERE json_type(settings, '$.mde.label_cap') IS NULL;

UPDATE experiments SET settings = json_set(settings, '$.learning.relax_beta', json('false'))
WHERE json_type(settings, '$.learning.relax_beta') IS NULL;

UPDATE models SET state = json_set(state, '$.hyperparameters.kernel', 'matern52')
WHERE json_type(state, '$.hyperparameters.kernel') IS NULL;

UPDATE models SET state = json_set(state, '$.noise_model.hyperparameters.kernel', 'matern52')
WHERE json_type(state, '$.noise_model') = 'object'
  AND json_type(state, '$.noise_model.hyperparameters.kernel') IS NULL;

UPDATE models SET hyperparameters = json_set(hyperparameters, '$.kernel', 'matern52')
WHERE json_type(hyperparameters, '$.kernel') IS NULL;

UPDATE models SET label_cap = COALESCE(
    (SELECT json_extract(e.settings, '$.mde.label_cap') FROM experiments e
     WHERE e.id = models.experiment_id
       AND json_type(e.settings, '$.mde.label_cap') IN ('integer', 'real')),
    0)
WHERE label_cap IS NULL;

UPDATE models SET label_cap_trials = '[]' WHERE label_cap_trials IS NULL;

UPDATE models SET label_cap_trials = (
    SELECT json_group_array(
        CASE WHEN json_type(value, '$.held_out_groups') IS NULL
             THEN json_set(value, '$.held_out_groups', 0) ELSE json(value) END)
    FROM json_each(models.label_cap_trials))
WHERE EXISTS (SELECT 1 FROM json_each(models.label_cap_trials)
              WHERE json_type(value, '$.held_out_groups') IS NULL);
