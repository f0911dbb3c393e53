"""Scale-out: many rollouts or optimisations at once on Ray (local cores, or a cluster by address).

``cases`` turns ``--grid`` / ``--samples`` into scene assignments, ``jobs`` holds what one
worker runs for one case, ``pool`` runs them on Ray actors. Only the commands that fan out
import this package (and Ray with it): ``cosim run`` on one scene never does.
"""
