-- ripplecal schema 13: several orders per map (issue 28).
-- maps.orders_json: null for a map of one order (every map before schema 13); else
-- [{"order": h, "cells": [{status, theta_cos, theta_sin, suppression_db, target_db, error, fill_theta_cos,
-- fill_theta_sin, fill_source}, ...]}, ...] for each further order, its cells in the order of map_cells
-- (udc_v, speed_rpm, torque_nm): the further orders' results, taken from each cell's result
-- (results.detail_json details.orders) with the fill rule applied per order, when the map was built.

ALTER TABLE maps ADD COLUMN orders_json TEXT;
