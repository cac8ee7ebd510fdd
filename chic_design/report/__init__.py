"""The report stage: ``report.md`` (:mod:`.markdown`) and the pictures beside it (:mod:`.pictures`)."""
