-- Job store of the serverless framework (issue 4), SQLite flavour.
-- Times are integer milliseconds since the epoch taken from the database's clock, so executors
-- with skewed clocks agree on leases and back-off. UUIDs are 16-byte BLOBs, JSON is TEXT.

CREATE TABLE campaigns (
    id                 BLOB PRIMARY KEY NOT NULL,
    name               TEXT NOT NULL,
    state              TEXT NOT NULL CHECK (state IN ('running', 'succeeded', 'failed', 'cancelled')),
    stage              TEXT NOT NULL,
    iteration          INTEGER NOT NULL,
    iterations_planned INTEGER NOT NULL,
    spec               TEXT NOT NULL,
    plan_state         TEXT NOT NULL,
    object_prefix      TEXT NOT NULL,
    error              TEXT,
    -- Queued + leased tasks of the current stage: the completion that takes it to 0 is the
    -- stage barrier (kept under the campaign row lock, so no count over tasks is needed).
    open_tasks         INTEGER NOT NULL DEFAULT 0,
    max_attempts       INTEGER NOT NULL CHECK (max_attempts >= 1),
    backoff_base_ms    INTEGER NOT NULL CHECK (backoff_base_ms >= 0),
    backoff_max_ms     INTEGER NOT NULL CHECK (backoff_max_ms >= 0),
    created_at_ms      INTEGER NOT NULL,
    updated_at_ms      INTEGER NOT NULL,
    finished_at_ms     INTEGER
);
CREATE INDEX campaigns_newest ON campaigns (created_at_ms DESC);

CREATE TABLE strips (
    campaign   BLOB NOT NULL REFERENCES campaigns (id) ON DELETE CASCADE,
    idx        INTEGER NOT NULL,
    id         TEXT NOT NULL,
    trajectory TEXT NOT NULL,
    uri        TEXT NOT NULL,
    points     INTEGER,
    PRIMARY KEY (campaign, idx)
);

CREATE TABLE trajectories (
    campaign BLOB NOT NULL REFERENCES campaigns (id) ON DELETE CASCADE,
    idx      INTEGER NOT NULL,
    id       TEXT NOT NULL,
    uri      TEXT NOT NULL,
    PRIMARY KEY (campaign, idx)
);

CREATE TABLE tiles (
    campaign BLOB NOT NULL REFERENCES campaigns (id) ON DELETE CASCADE,
    key      TEXT NOT NULL,
    strips   TEXT NOT NULL, -- JSON array of strip ids
    points   INTEGER NOT NULL,
    PRIMARY KEY (campaign, key)
);

CREATE TABLE iterations (
    campaign       BLOB NOT NULL REFERENCES campaigns (id) ON DELETE CASCADE,
    iteration      INTEGER NOT NULL,
    stats          TEXT NOT NULL,
    recorded_at_ms INTEGER NOT NULL,
    PRIMARY KEY (campaign, iteration)
);

CREATE TABLE tasks (
    id                  INTEGER PRIMARY KEY,
    campaign            BLOB NOT NULL REFERENCES campaigns (id) ON DELETE CASCADE,
    stage               TEXT NOT NULL,
    iteration           INTEGER NOT NULL,
    kind                TEXT NOT NULL,
    key                 TEXT NOT NULL,
    input               TEXT NOT NULL,
    state               TEXT NOT NULL CHECK (state IN ('queued', 'leased', 'done', 'dead', 'cancelled')),
    attempt             INTEGER NOT NULL DEFAULT 0,
    not_before_ms       INTEGER NOT NULL,
    lease_token         BLOB,
    lease_expires_at_ms INTEGER,
    worker              TEXT,
    result              TEXT,
    error               TEXT,
    created_at_ms       INTEGER NOT NULL,
    updated_at_ms       INTEGER NOT NULL,
    finished_at_ms      INTEGER,
    UNIQUE (campaign, stage, iteration, kind, key)
);
-- Claim scans queued tasks oldest first; reconcile scans leased tasks by expiry. Per-campaign and
-- per-stage look-ups use the UNIQUE index's prefix: every index on `state` would be rewritten by
-- each claim and completion (no HOT update), so there are no more of them.
CREATE INDEX tasks_queued ON tasks (id) WHERE state = 'queued';
CREATE INDEX tasks_leased ON tasks (lease_expires_at_ms) WHERE state = 'leased';

CREATE TABLE task_outputs (
    task_id    INTEGER NOT NULL REFERENCES tasks (id) ON DELETE CASCADE,
    campaign   BLOB NOT NULL REFERENCES campaigns (id) ON DELETE CASCADE,
    name       TEXT NOT NULL,
    object_key TEXT NOT NULL,
    PRIMARY KEY (task_id, name)
);
CREATE INDEX task_outputs_campaign ON task_outputs (campaign);

CREATE TABLE events (
    id       INTEGER PRIMARY KEY AUTOINCREMENT,
    campaign BLOB NOT NULL REFERENCES campaigns (id) ON DELETE CASCADE,
    at_ms    INTEGER NOT NULL,
    kind     TEXT NOT NULL,
    task_id  INTEGER,
    message  TEXT NOT NULL
);
CREATE INDEX events_campaign ON events (campaign, id);
