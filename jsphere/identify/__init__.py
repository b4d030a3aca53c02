"""System identification: free parameters, the least-squares fit (single and multiple
shooting), the verdict on its residuals."""
