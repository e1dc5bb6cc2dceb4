"""Pure fusion algorithms: motion models, Kalman filters, association, tracking, compensation, prediction, ROIF."""
