"""`polargs ablate` / `polargs demo` machinery: variants, grid cells, the local executor, gathering and the report (docs/ablation.md)."""
