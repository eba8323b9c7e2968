"""Physics diagnosis: a MuJoCo model as a parametrised simulator (mjx_model), measured data from
C MuJoCo with planted changes (measured), its errors (errors) and the identification of the
quantities that explain them (identify). docs/DIAGNOSIS.md, "Physics"."""
