-- The stage barrier no longer counts open tasks on the campaign row: that update held the
-- campaign's row lock through every completion's commit (WAL flush), so all completions of one
-- campaign queued behind each other. A completion now commits without touching the campaign and
-- then looks for open tasks of its stage through this index (issue 4, queue throughput).
ALTER TABLE campaigns DROP COLUMN open_tasks;
-- Open (queued or leased) tasks by stage. Claims and completions change `state`, so they are never
-- HOT updates and already rewrite every index entry; this one only gets entries for open rows.
CREATE INDEX tasks_open ON tasks (campaign, stage, iteration, id) WHERE state IN ('queued', 'leased');
