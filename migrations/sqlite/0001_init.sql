-- splatmark service schema (issue 5). Times are RFC 3339 UTC text with milliseconds
-- ('2026-12-01T16:09:21.123Z'), so they compare as strings. Ids are hyphenated UUID text.

-- Key/value facts about this database (the master-key check value).
CREATE TABLE meta (
    key   TEXT PRIMARY KEY,
    value BLOB NOT NULL
) WITHOUT ROWID;

-- Uploaded originals and published watermarked scenes. `seq` is a compact handle for the
-- attribution rows; `source_job_id` UNIQUE is what makes publishing exactly-once.
CREATE TABLE assets (
    seq            INTEGER PRIMARY KEY,
    id             TEXT NOT NULL UNIQUE,
    owner          TEXT NOT NULL,
    kind           TEXT NOT NULL CHECK (kind IN ('original', 'watermarked')),
    parent_id      TEXT REFERENCES assets(id),
    source_job_id  TEXT UNIQUE REFERENCES jobs(id),
    sha256         TEXT NOT NULL,
    size           INTEGER NOT NULL CHECK (size >= 0),
    format         TEXT NOT NULL,
    file_name      TEXT,
    gaussians      INTEGER NOT NULL CHECK (gaussians >= 0),
    sh_degree      INTEGER NOT NULL CHECK (sh_degree BETWEEN 0 AND 3),
    cameras_sha256 TEXT,
    cameras_format TEXT,
    report         TEXT,
    created_at     TEXT NOT NULL
);
CREATE INDEX assets_parent ON assets(parent_id, created_at);

-- Each watermarked asset's message, XChaCha20-Poly1305 under the master key (AAD = asset id).
CREATE TABLE keys (
    asset_id   TEXT PRIMARY KEY REFERENCES assets(id),
    bits       INTEGER NOT NULL,
    nonce      BLOB NOT NULL,
    ciphertext BLOB NOT NULL,
    created_at TEXT NOT NULL
) WITHOUT ROWID;

-- The watermarking queue. `failed` = will retry at not_before; `dead` = out of attempts.
CREATE TABLE jobs (
    id               TEXT PRIMARY KEY,
    asset_id         TEXT NOT NULL REFERENCES assets(id),
    owner            TEXT NOT NULL,
    bits             INTEGER NOT NULL CHECK (bits > 0),
    message_nonce    BLOB NOT NULL,
    message_ct       BLOB NOT NULL,
    options          TEXT NOT NULL,
    idempotency_key  TEXT,
    state            TEXT NOT NULL
        CHECK (state IN ('queued', 'running', 'done', 'failed', 'dead', 'cancelled')),
    phase            TEXT,
    step             INTEGER NOT NULL DEFAULT 0,
    total            INTEGER NOT NULL DEFAULT 0,
    eta_seconds      REAL,
    attempts         INTEGER NOT NULL DEFAULT 0,
    max_attempts     INTEGER NOT NULL CHECK (max_attempts > 0),
    not_before       TEXT NOT NULL,
    lease_token      TEXT,
    lease_expires_at TEXT,
    worker           TEXT,
    heartbeat_at     TEXT,
    error            TEXT,
    result_asset_id  TEXT REFERENCES assets(id),
    created_at       TEXT NOT NULL,
    updated_at       TEXT NOT NULL
);
CREATE UNIQUE INDEX jobs_idempotency ON jobs(owner, idempotency_key)
    WHERE idempotency_key IS NOT NULL;
CREATE INDEX jobs_ready ON jobs(state, not_before, created_at);
CREATE INDEX jobs_lease ON jobs(state, lease_expires_at);

-- Per-Gaussian attribution of a watermarked asset. `role` 0 carrier, 1 compensator,
-- 2 untouched; `flags` bit 0 feasible, bits 1-2 seed (0 none, 1 proximity, 2 WM0), bit 3
-- wm_grad_share present; `data` 22 little-endian f32 (r, uncertainty, quality, utility,
-- visibility, mask_wm, mask_vis, wm_grad_share) = exact round trip. utility, visibility and
-- wm_grad_share are repeated as REAL for aggregates (NULL for NaN / absent).
CREATE TABLE attribution (
    asset_seq     INTEGER NOT NULL REFERENCES assets(seq),
    idx           INTEGER NOT NULL,
    role          INTEGER NOT NULL,
    parent        INTEGER NOT NULL,
    child         INTEGER NOT NULL,
    flags         INTEGER NOT NULL,
    utility       REAL,
    visibility    REAL,
    wm_grad_share REAL,
    data          BLOB NOT NULL,
    PRIMARY KEY (asset_seq, idx)
) WITHOUT ROWID;
CREATE INDEX attribution_role ON attribution(asset_seq, role, idx);

-- Dispute verifications (who asked, what images, what was decided).
CREATE TABLE verifications (
    id           TEXT PRIMARY KEY,
    actor        TEXT NOT NULL,
    asset_id     TEXT REFERENCES assets(id),
    images       INTEGER NOT NULL,
    image_sha256 TEXT NOT NULL,
    result       TEXT NOT NULL,
    audit_id     INTEGER NOT NULL REFERENCES audit(id),
    created_at   TEXT NOT NULL
);

-- Append-only audit log; hash = sha256(prev_hash || canonical row bytes), see store::audit.
CREATE TABLE audit (
    id        INTEGER PRIMARY KEY,
    at        TEXT NOT NULL,
    actor     TEXT NOT NULL,
    action    TEXT NOT NULL,
    asset_id  TEXT,
    job_id    TEXT,
    details   TEXT NOT NULL,
    prev_hash TEXT NOT NULL,
    hash      TEXT NOT NULL UNIQUE
);
CREATE INDEX audit_asset ON audit(asset_id, id);
CREATE INDEX audit_action ON audit(action, id);
CREATE INDEX audit_actor ON audit(actor, id);
CREATE INDEX audit_at ON audit(at);
CREATE TRIGGER audit_no_update BEFORE UPDATE ON audit
BEGIN
    SELECT RAISE(ABORT, 'audit log is append-only');
END;
CREATE TRIGGER audit_no_delete BEFORE DELETE ON audit
BEGIN
    SELECT RAISE(ABORT, 'audit log is append-only');
END;

-- Bearer API keys: only the SHA-256 of the token is stored. scopes: comma-separated.
CREATE TABLE api_keys (
    id           TEXT PRIMARY KEY,
    name         TEXT NOT NULL,
    token_sha256 TEXT NOT NULL UNIQUE,
    scopes       TEXT NOT NULL,
    created_at   TEXT NOT NULL,
    revoked_at   TEXT
);
