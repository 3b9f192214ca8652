"""The optimizer around the GP (``cpgjax.gp``): Algorithm 1, the acquisition, the β schedule, the static
configuration and a black-box maximize loop."""
