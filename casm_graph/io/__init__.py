"""Reading what users hand over (log bundles, the MRCLAM data set) and writing runs all or nothing."""
