-- Every claim added an entry to `tasks_leased`, and the generic plans of the statements that find a
-- leased task by id and lease token (completion, heartbeat) scanned this partial index, which
-- looks tiny to a planner that last analysed the table while nothing was leased, instead of the
-- primary key: a walk over every lease of every campaign (and over the dead entries of earlier
-- ones) per completion. The reconciler finds expired leases through `tasks_open` instead.
DROP INDEX tasks_leased;
