"""The experiments, by trade: :mod:`.runners` (what runs), :mod:`.storage` (where results live), :mod:`.analysis`
(what they say) and :mod:`.sweep` (grids of runs on Ray)."""
