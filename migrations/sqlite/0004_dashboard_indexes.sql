-- Reads of the dashboard: a proposal's executing trajectory (the runs table joins proposals to
-- trajectories by `proposal_id`), without a scan of the experiment's trajectories per proposal.
CREATE INDEX trajectories_by_proposal ON trajectories (proposal_id);
