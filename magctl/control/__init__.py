"""Controller blocks: tracker, visual servo, path planner, push tasks."""
