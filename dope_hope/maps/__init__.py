"""The map codec: the map<->image grid, targets (encode) and decoding (peaks, grouping)."""
