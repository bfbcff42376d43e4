//! Public file formats at the edge: campaign manifest, trajectory CSV, LAS/LAZ strips.
