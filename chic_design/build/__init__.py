"""The build stage: :func:`.pipeline.build_design`, its atomic export folders (:mod:`.folders`) and picture worker (:mod:`.workers`)."""
