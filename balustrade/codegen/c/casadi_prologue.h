/* balustrade: CasADi's runtime templates leave some parameters unused; silence that one
   warning for this generated file only, so that everything builds with -Wall -Wextra -Werror */
#if defined(__GNUC__) || defined(__clang__)
#pragma GCC diagnostic ignored "-Wunused-parameter"
#endif
