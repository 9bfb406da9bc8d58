"""radfield.edit: editing a trained field through its tetrahedral cage (Neural Impostor on
splattable neural primitives). A library over primitives and cages: it never imports a stage.

Modules: field (the editable field and its files), select (selections of points), spec (the YAML
edit spec and its registry of operations), one module per operation family."""
