-- The sweep of a finished campaign's objects of lost attempts, made durable. The executor that
-- finishes a campaign cleans up at once, but it may die mid-way, and attempts cancelled with the
-- campaign may still write afterwards; the reconciler of any executor therefore sweeps every
-- finished campaign once more after a grace period. `sweep_lease_until_ms` keeps executors from
-- sweeping the same campaign together; `swept_at_ms` (NULL until then) marks it done.
ALTER TABLE campaigns ADD COLUMN sweep_lease_until_ms INTEGER;
ALTER TABLE campaigns ADD COLUMN swept_at_ms INTEGER;
