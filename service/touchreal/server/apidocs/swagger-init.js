// Starts Swagger UI on the /docs page (an external file: the page's CSP allows no inline script).
// Loaded after #swagger-ui, whose data-openapi-url is the OpenAPI document (relative to the page).
"use strict";
SwaggerUIBundle({
  url: document.getElementById("swagger-ui").dataset.openapiUrl,
  dom_id: "#swagger-ui",
  layout: "BaseLayout",
  deepLinking: true,
  showExtensions: true,
  showCommonExtensions: true,
  validatorUrl: null,  // no badge from the public validator: the page makes no request off this host
  presets: [SwaggerUIBundle.presets.apis, SwaggerUIBundle.SwaggerUIStandalonePreset],
});
