"""The report stage: ``report.md`` (:mod:`.markdown`), the pictures beside it (:mod:`.pictures`) and the fill
guide (:mod:`.fill_guide`)."""
