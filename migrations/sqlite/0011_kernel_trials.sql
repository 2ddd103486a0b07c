-- With `mde.kernel: "auto"` each fit tries every Matérn kernel and keeps the one whose fit has
-- the highest log marginal likelihood; each candidate's (JSON: [{kernel,
-- log_marginal_likelihood}]) is kept with the version. Versions fitted before had one kernel.
ALTER TABLE models ADD COLUMN kernel_trials TEXT NOT NULL DEFAULT '[]';
