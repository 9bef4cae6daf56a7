-- ripplecal schema 12: injection off per map cell (issue 27: never worse than no compensation).
-- map_cells.injection_off: 1 where the drive is to inject nothing in any interval of the LUT that has this
-- cell as a corner of non-zero weight (LUT image flag 3, format_version 4: drivers/lut_image.py); the cell
-- keeps its result and fill for the record. 0 (every cell before schema 12): as before.

ALTER TABLE map_cells ADD COLUMN injection_off INTEGER NOT NULL DEFAULT 0 CHECK (injection_off IN (0, 1));
