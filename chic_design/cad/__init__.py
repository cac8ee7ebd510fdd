"""The CAD stage: channel arithmetic (:mod:`.channels`), the parts of any family (:mod:`.parts`), their files
(:mod:`.export`)."""

#: The three printed parts, in the order they are made and written.
PART_NAMES = ("body", "cap_top", "cap_bottom")
