-- A proposal request past its planning deadline is recorded as a refused run too, beside those
-- answered `no_plan`: why each was refused. Refusals recorded before were all `no_plan`.
ALTER TABLE refusals ADD COLUMN reason TEXT NOT NULL DEFAULT 'no_plan';
