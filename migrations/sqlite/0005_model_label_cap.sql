-- The label cap (units of d_max; 0 = raw labels) a version was fitted with, chosen at the fit
-- when the experiment's `mde.label_cap` is "auto", and every candidate's held-out judgement of
-- the training transitions (JSON). NULL for versions fitted before caps were recorded: those
-- were fitted with the experiment's fixed cap (or raw labels when it has none).
ALTER TABLE models ADD COLUMN label_cap REAL;
ALTER TABLE models ADD COLUMN label_cap_trials TEXT;
