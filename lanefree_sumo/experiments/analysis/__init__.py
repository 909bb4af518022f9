"""What the results say: reports and learning curves, the paper's claims checked, comparisons and effects of
variants, bootstrap statistics, the interpretation study's score, the paper's reference numbers."""
