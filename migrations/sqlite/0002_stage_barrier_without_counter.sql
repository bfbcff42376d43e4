-- The stage barrier no longer counts open tasks on the campaign row (see the PostgreSQL
-- migration of the same name): a completion looks for open tasks of its stage through this index.
ALTER TABLE campaigns DROP COLUMN open_tasks;
CREATE INDEX tasks_open ON tasks (campaign, stage, iteration, id) WHERE state IN ('queued', 'leased');
