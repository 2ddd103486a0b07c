-- A fit whose estimated time exceeds the server's budget (`--max-fit-seconds`) is refused and
-- recorded like one beyond the memory budget: its estimated seconds and the budget. Refusals
-- made before (all for memory) have neither.
ALTER TABLE fit_refusals ADD COLUMN needed_seconds REAL;
ALTER TABLE fit_refusals ADD COLUMN budget_seconds REAL;
