"""Monte-Carlo studies: sampled robots and actuators, batched runs, resumable stores."""
