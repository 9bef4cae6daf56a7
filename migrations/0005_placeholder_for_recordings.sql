-- PLACEHOLDER on branch issue11-validate only: number 5 belongs to the recordings helper's migration.
-- It lets 0006 run on this branch; drop this file when merging (the real 0005 takes its place).
CREATE TABLE IF NOT EXISTS _placeholder_0005 (id INTEGER PRIMARY KEY);
DROP TABLE _placeholder_0005;
