-- A `continue` replayed under its Idempotency-Key answers the proposal its first call made,
-- whatever has happened to it since, instead of planning (and leasing) a new one.
ALTER TABLE idempotency_keys ADD COLUMN continued_proposal_id BIGINT REFERENCES proposals(id);
